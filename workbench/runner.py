"""Running an estimator over dataset frames, with a progress bar on stderr, and where its results may go.

Results are written frame by frame (``ResultsFile``), so a crash or Ctrl-C loses at most the frame in progress,
and ``--resume`` skips the frames already written. ``check_results_out`` decides, before any work, whether the
output path may be written: never inside a dataset's scene or models folder, never over a file that is not a
results CSV of ours unless forced.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Callable

from tqdm import tqdm

from workbench import bop
from workbench.bop import ResultRow
from workbench.checks import check_workers
from workbench.errors import InputError
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
    on_frame: Callable[[list[ResultRow]], None] | None = None,
) -> list[ResultRow]:
    """Estimate every (scene_id, im_id) frame -> BOP result rows. One worker pool per frame (the problem, hence
    the renderer's camera and the physics table, differs per frame). ``on_frame(rows)`` gets each frame's rows as
    soon as it is done (to write them)."""
    config.validate()  # before any file is read or worker started
    check_workers(workers)
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
        frame_rows = result_rows(frame, problem, best, scores, time.perf_counter() - t0)
        if on_frame is not None:
            on_frame(frame_rows)
        rows += frame_rows
    return rows


def dataset_folder_of(path: Path) -> Path | None:
    """The scene or models folder of a BOP dataset that ``path`` (resolved) lies in, if any: a folder holding
    scene_camera.json or models_info.json, or a depth/rgb/mask folder below one."""
    for folder in Path(path).resolve().parents:
        if (folder / "scene_camera.json").is_file() or (folder / "models_info.json").is_file():
            return folder
    return None


def check_results_out(out: Path, force: bool = False, resume: bool = False) -> list[str]:
    """Check, before any work, that ``estimate`` may write its results CSV at ``out`` -> the data lines already
    there to keep as they are (``resume``; else none). Refused with InputError: a folder, a path below a file, an unwritable place,
    anything inside a dataset's scene or models folder (even with ``force``), and an existing file that is not a
    results CSV of ours unless ``force``."""
    out = Path(out)
    if force and resume:
        raise InputError("--resume", "--resume keeps the results in --out and --force replaces the file: pass one")
    target = out.resolve()
    inside = dataset_folder_of(target)
    if inside is not None:
        raise InputError(out, f"lies in the dataset folder {inside}: results are never written among a dataset's "
                              "scenes or models; choose an --out outside them")
    if target.is_dir():
        raise InputError(out, "is a folder: name a file for the results, e.g. results.csv")
    folder = target.parent
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir():
        raise InputError(out, f"{folder} is a file, not a folder: the results cannot be written below it")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(out, f"no permission to write in {folder}")
    if not target.exists():
        return []
    if not target.is_file():
        raise InputError(out, "is not a regular file: choose another --out")
    if not os.access(target, os.W_OK):
        raise InputError(out, "no permission to replace this file")
    try:
        bop.read_results_csv(target)
        ours = [line for line in target.read_text().splitlines()[1:] if line.strip()]
    except (InputError, OSError, UnicodeDecodeError):
        ours = None
    if resume:
        if ours is None:
            raise InputError(out, "is not a results CSV written by `workbench estimate`: there is nothing to resume")
        return ours
    if ours is None and not force:
        raise InputError(out, "exists and is not a results CSV written by `workbench estimate`; it was left as it "
                              "is. Choose another --out, or pass --force to replace it")
    return []


class ResultsFile:
    """The results CSV of a run, rewritten whole (atomically) after every frame: the file always holds every
    finished frame, in frame order, and nothing half-written. Lines kept from an earlier run (``lines``, checked
    by ``check_results_out``) stay exactly as they were."""

    def __init__(self, path: Path, lines: list[str] | None = None):
        self.path = Path(path)
        self.lines = list(lines or [])

    @staticmethod
    def _frame(line: str) -> tuple[int, int]:
        scene_id, im_id = line.split(",", 2)[:2]
        return int(scene_id), int(im_id)

    def done(self) -> set[tuple[int, int]]:
        """(scene_id, im_id) of the frames already in the file."""
        return {self._frame(line) for line in self.lines}

    def add(self, rows: list[ResultRow]) -> None:
        self.lines = sorted(self.lines + bop.results_csv_lines(rows), key=self._frame)
        bop.write_results_lines(self.path, self.lines)
