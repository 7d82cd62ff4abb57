"""Running an estimator over dataset frames, with a progress bar on stderr.

Frames run one after another here (``--engine local``) or as Ray tasks over a cluster (``--engine ray``), both by
``run.frames.run_frames``; each frame's rows go to ``on_frame`` as soon as it is done, for the results files of
``io/results.py`` to write.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
from tqdm import tqdm

from workbench.errors import InputError
from workbench.evaluation import ChunkedEvaluator, Evaluator, WorkerCrashed, make_evaluator
from workbench.evaluation.local import prepare_meshes
from workbench.evaluation.pool import check_workers
from workbench.evaluation.ray import RayConfig  # imports Ray only when used
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator, object_confidence
from workbench.io.results import ResultRow, posterior_rows, result_rows
from workbench.meshes.heavy import announced, announced_if, heavy_models
from workbench.problem.build import load_bop_problem
from workbench.problem.problem import Problem, ProblemConfig
from workbench.problem.scene import Frame
from workbench.run.frames import FrameFailure, FrameKey, run_frames

# Where stderr is not a terminal (a log file), a frame's progress is one line at most this often (s): a six-object
# frame takes about a minute, and a log that says nothing for that long looks stuck.
LOG_EVERY_S = 10.0


class FramePool:
    """One evaluator for a run's frames, one after another (``evaluator_for`` of ``estimate_frame``): the first
    frame starts it, each later frame retargets it (``PoolEvaluator.retarget``: each worker builds its renderer and
    physics for the new frame in the process it already runs), which saves starting the worker processes and
    importing their libraries again for every frame. A frame's results do not depend on the frames its workers
    evaluated before (physics and rendering are built anew per problem, as in ``track``)."""

    def __init__(self, workers: int, max_retries: int):
        self.workers, self.max_retries = workers, max_retries
        self.evaluator: Evaluator | None = None

    def __call__(self, problem: Problem) -> Evaluator:
        if self.evaluator is None:
            self.evaluator = make_evaluator(problem, self.workers, max_retries=self.max_retries)
        else:
            self.evaluator.retarget(problem)
        return Lent(self.evaluator)

    def close(self) -> None:
        if self.evaluator is not None:
            self.evaluator.close()
            self.evaluator = None


class Lent:
    """An evaluator lent to one frame: closing it leaves it running for the next (``FramePool``)."""

    def __init__(self, evaluator: Evaluator):
        self._evaluator = evaluator

    def __getattr__(self, name):
        return getattr(self._evaluator, name)

    def close(self) -> None:
        pass


def estimate_frame(
    dataset: Path,
    scene_id: int,
    im_id: int,
    config: EstimatorConfig,
    problem_config: ProblemConfig,
    evaluator_for: Callable[[Problem], Evaluator],
    split: str | None = None,
    object_ids: list[int] | None = None,
    early_stop: bool = True,
    show_progress: bool = False,
) -> list[ResultRow]:
    """Estimate one frame with the evaluator ``evaluator_for(problem)`` (closed afterwards) -> its BOP result rows,
    ``time`` the frame's wall seconds: each object's modes, best first, with their probabilities
    (``io.results.posterior_rows``; one row per object, scored by ``object_confidence``, where the search gives no
    posterior). What the view leaves open is said in one line on stderr (``Posterior.summary``).
    ``show_progress``: a progress bar of its iterations on stderr when stderr is a terminal, opened once the frame
    has loaded (a bad frame fails before any bar)."""
    t0 = time.perf_counter()
    # Loading a real frame and starting its workers took 14-24 s without a word: said when it takes a while.
    starting = f"loading scene {scene_id} frame {im_id} and starting its evaluation"
    with announced(starting, cached=False) if show_progress else contextlib.nullcontext():
        frame, problem = load_bop_problem(dataset, scene_id, im_id, split, object_ids, problem_config)
        # A frame with a model of over heavy.HEAVY_FACES faces says what it does while it does it: simplifying the
        # model (once: cached), starting the workers (each takes the whole model) and estimating (on a terminal,
        # its bar).
        heavy = heavy_models(problem.models)
        if heavy:
            prepare_meshes(problem)  # announced on its own; the evaluators then read the cache
        with announced_if(heavy, f"starting the evaluation of scene {scene_id} frame {im_id}"):
            evaluator = evaluator_for(problem)
    try:
        with announced_if(heavy if not (show_progress and sys.stderr.isatty()) else "",
                          f"estimating scene {scene_id} frame {im_id}"):
            estimator, best = run_estimator(Estimator(problem, config, evaluator), f"scene {scene_id} frame {im_id}",
                                            early_stop, show_progress, started=t0)
    finally:
        evaluator.close()
    if estimator.posterior is not None:  # one line per frame: what the view leaves open
        print(f"scene {scene_id} frame {im_id}: {estimator.posterior.summary(problem)} "
              f"[posterior {estimator.posterior.seconds:.1f} s{cut_note(estimator.cut_short)}]", file=sys.stderr)
    return estimator_rows(frame, problem, estimator, best, time.perf_counter() - t0)


def cut_note(cut_short: str | None) -> str:
    """What a frame's line says of its budget: nothing where the run finished."""
    return "" if cut_short is None else f"; the budget cut short: {cut_short}"


def run_estimator(estimator: Estimator, desc: str, early_stop: bool = True, show_progress: bool = False,
                  started: float | None = None) -> tuple[Estimator, np.ndarray]:
    """Run ``estimator`` to its iteration budget (or convergence, ``early_stop``, or its time budget counted from
    ``started``, see ``Estimator.run``) -> (it, its settled estimate (K, 4, 4) table frame). ``show_progress``: a
    progress bar named ``desc`` on stderr when stderr is a terminal. Without a bar, a plain line says how far the
    run is every LOG_EVERY_S seconds: a tracked frame asked for 100,000 iterations ran minutes without one."""
    # On a terminal only (disable=None): in a log file the bar's carriage returns would share lines with the
    # messages after it, so there a plain line says how far the frame is, at most every LOG_EVERY_S seconds.
    t0 = last = time.perf_counter()
    done = 0
    with tqdm(total=estimator.config.iterations + 1, desc=desc, file=sys.stderr, leave=False,
              disable=None if show_progress else True) as bar:
        def progress(report):
            nonlocal last, done
            done += 1
            bar.update(1)
            bar.set_postfix(best=f"{report.best_loglik:.0f}", ess=f"{report.ess:.0f}")
            now = time.perf_counter()
            if bar.disable and now - last >= LOG_EVERY_S:
                last = now
                print(f"{desc}: step {done} of at most {bar.total} after {now - t0:.0f} s "
                      f"(best {report.best_loglik:.0f})", file=sys.stderr, flush=True)
        best = estimator.run(stop_on_convergence=early_stop, callback=progress, started=started)
    return estimator, best


def estimator_rows(frame: Frame, problem: Problem, estimator: Estimator, best: np.ndarray, seconds: float
                   ) -> list[ResultRow]:
    """A finished estimator's BOP result rows, ``time`` = ``seconds``: each object's modes, best first, with their
    probabilities (``io.results.posterior_rows``); one row per object, scored by ``object_confidence``, where the
    search gives no posterior."""
    if estimator.posterior is not None:
        return posterior_rows(frame, problem, estimator.posterior, seconds)
    scores = object_confidence(problem, estimator.particles.projected, estimator.weights(), best)
    return result_rows(frame, problem, best, scores, seconds)


def estimate_frame_task(scene_id: int, im_id: int, dataset: Path, config: EstimatorConfig,
                        problem_config: ProblemConfig, workers: int, split: str | None,
                        object_ids: list[int] | None, early_stop: bool) -> list[ResultRow]:
    """One frame as a Ray task, on one CPU: its batches split as ``workers`` local processes would split them
    (``ChunkedEvaluator``), so that its rows equal those of `--engine local` with the same ``workers``."""
    # One llvmpipe thread, as in a local pool's workers: the other tasks keep the other cores busy.
    os.environ.setdefault("LP_NUM_THREADS", "1")
    return estimate_frame(dataset, scene_id, im_id, config, problem_config,
                          lambda problem: ChunkedEvaluator(problem, workers), split, object_ids, early_stop)


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
    ray: RayConfig | None = None,
    on_failure: Callable[[FrameFailure], None] | None = None,
    max_retries: int = 3,
) -> list[ResultRow]:
    """Estimate every (scene_id, im_id) frame -> BOP result rows, in the order the frames finished.
    ``on_frame(rows)`` gets each frame's rows as soon as it is done (to write them).

    Locally (``ray`` None) frames run one after another, each on a worker pool of its own (the problem, hence the
    renderer's camera and the physics table, differs per frame), and the first bad frame raises. With ``ray`` (a
    RayConfig) every frame is a Ray task (``estimate_frame_task``); a frame that fails goes to ``on_failure`` (if
    None: raised as InputError once the others are done) and the others go on. Locally, a dead evaluation worker
    is started again and its part of the batch retried, up to ``max_retries`` times per batch (then InputError)."""
    config.validate()  # before any file is read or worker started
    check_workers(workers)
    rows: list[ResultRow] = []
    failures: list[FrameFailure] = []
    finished, said = 0, time.perf_counter()

    def done(_frame: FrameKey, frame_rows: list[ResultRow]) -> None:
        nonlocal finished, said
        if on_frame is not None:
            on_frame(frame_rows)
        rows.extend(frame_rows)
        # Quick frames say nothing of their own: a run of 500 went 100 s without a line though 67 were done.
        finished += 1
        if time.perf_counter() - said >= LOG_EVERY_S:
            said = time.perf_counter()
            print(f"{finished} of {len(frames)} frame(s) done", file=sys.stderr, flush=True)

    pool = FramePool(workers, max_retries)

    def here(scene_id: int, im_id: int) -> list[ResultRow]:
        try:
            return estimate_frame(dataset, scene_id, im_id, config, problem_config, pool, split, object_ids,
                                  early_stop, show_progress=True)
        except WorkerCrashed as err:
            raise InputError(f"scene {scene_id} frame {im_id}",
                             f"{err}; the frames before it are kept (run again with --resume)") from None

    try:
        run_frames(frames, here, estimate_frame_task,
                   (Path(dataset).resolve(), config, problem_config, workers, split, object_ids, early_stop),
                   ray, done, on_failure or failures.append)
    finally:
        pool.close()
    if failures:
        raise InputError(dataset, "; ".join(f"scene {f.frame[0]} frame {f.frame[1]}: {f.problem}"
                                            for f in failures))
    return rows
