"""Running an estimator over dataset frames, with a progress bar on stderr."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from tqdm import tqdm

from workbench.bop import ResultRow
from workbench.estimators import Estimator, EstimatorConfig, object_confidence
from workbench.evaluation import make_evaluator
from workbench.pipeline import load_bop_problem, result_rows
from workbench.problem import ProblemConfig


def estimate_frames(
    dataset: Path,
    frames: list[tuple[int, int]],
    config: EstimatorConfig,
    problem_config: ProblemConfig,
    workers: int,
    split: str | None = None,
    object_ids: list[int] | None = None,
    early_stop: bool = True,
) -> list[ResultRow]:
    """Estimate every (scene_id, im_id) frame -> BOP result rows. One worker pool per frame (the problem, hence
    the renderer's camera and the physics table, differs per frame)."""
    config.validate()  # before any file is read or worker started
    rows: list[ResultRow] = []
    for scene_id, im_id in frames:
        t0 = time.perf_counter()
        frame, problem = load_bop_problem(dataset, scene_id, im_id, split, object_ids, problem_config)
        evaluator = make_evaluator(problem, workers)
        try:
            estimator = Estimator(problem, config, evaluator)
            with tqdm(total=config.iterations + 1, desc=f"scene {scene_id} frame {im_id}", file=sys.stderr,
                      leave=False) as bar:
                def progress(report):
                    bar.update(1)
                    bar.set_postfix(best=f"{report.best_loglik:.0f}", ess=f"{report.ess:.0f}")
                best = estimator.run(stop_on_convergence=early_stop, callback=progress)
        finally:
            evaluator.close()
        scores = object_confidence(problem, estimator.projected, estimator.weights(), best)
        rows += result_rows(frame, problem, best, scores, time.perf_counter() - t0)
    return rows
