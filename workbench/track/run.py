"""Running ``workbench track``'s sequences: one after another here (``--engine local``), or each sequence as one Ray
task, several side by side (``--engine ray``). A sequence's frames depend on each other (each starts from the one
before), so a sequence is never split: it is the unit of work, as a frame is for ``estimate``.

As for ``estimate``, results do not depend on the engine: a sequence task evaluates its batches with a
``ChunkedEvaluator`` (each batch split as ``--workers`` local processes would split it, evaluated in turn on the
task's one CPU), given each next frame's problem as the local pool is (``retarget``); the estimator's seed is the
config's. So a run on Ray writes the same poses and scores as one here with the same ``--workers`` (only the time
column differs).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Callable

from tqdm import tqdm

from workbench.evaluation import ChunkedEvaluator
from workbench.evaluation.ray import RayConfig  # imports Ray only when used
from workbench.inference.config import EstimatorConfig
from workbench.problem.problem import Problem, ProblemConfig
from workbench.run.frames import FrameFailure, run_ray_tasks
from workbench.track.config import TrackConfig
from workbench.track.sequence import FrameResult, Tracker, track_frames


def track_sequence_task(scene_id: int, frames: list[int], done: set[int], dataset: Path, config: EstimatorConfig,
                        track: TrackConfig, problem_config: ProblemConfig, workers: int, split: str | None,
                        object_ids: list[int] | None, early_stop: bool) -> list[FrameResult]:
    """One sequence (scene ``scene_id``'s ``frames``, those in ``done`` skipped) as a Ray task, on one CPU: one
    ``ChunkedEvaluator`` of ``workers`` parts for the whole sequence, retargeted to each frame's problem, as the
    local engine's pool is. -> each frame's result, in order (the frames' lines are the caller's to print)."""
    os.environ.setdefault("LP_NUM_THREADS", "1")  # one llvmpipe thread: the other tasks keep the other cores busy
    evaluator: ChunkedEvaluator | None = None

    def evaluator_for(problem: Problem) -> ChunkedEvaluator:
        nonlocal evaluator
        if evaluator is None:
            evaluator = ChunkedEvaluator(problem, workers)
        elif evaluator.problem is not problem:
            evaluator.retarget(problem)
        return evaluator

    tracker = Tracker(dataset, scene_id, frames, config, track, problem_config, workers, split, object_ids,
                      early_stop, evaluator_for=evaluator_for)
    try:
        return track_frames(tracker, frames, done, lambda result: None, echo=False)
    finally:
        if evaluator is not None:
            evaluator.close()


def track_sequences(dataset: Path, sequences: dict[int, list[int]], done: dict[int, set[int]],
                    config: EstimatorConfig, track: TrackConfig, problem_config: ProblemConfig, workers: int,
                    split: str | None, object_ids: list[int] | None, early_stop: bool, max_retries: int,
                    on_frame: Callable[[FrameResult], None], ray: RayConfig | None,
                    on_failure: Callable[[FrameFailure], None]) -> int:
    """Track every sequence (scene id -> its frames, in order; ``done``: per scene the frames a resumed run keeps)
    and hand each frame's result to ``on_frame`` -> the number of frames tracked.

    Locally (``ray`` None): one sequence after another on a pool of ``workers`` processes each, every frame's result
    as soon as it is done; the first bad input ends the run with its error. With ``ray``: every sequence a Ray task
    (``track_sequence_task``, one CPU), as many at once as the cluster has CPUs; a sequence's frames come when its
    task ends, their lines printed then; a sequence that failed goes to ``on_failure`` (``FrameFailure`` of
    (scene, its first frame)) and the others go on. A task whose worker died is run again from its first frame,
    up to ``ray.max_retries`` times."""
    count = 0
    if ray is None:
        for scene_id, frames in sequences.items():
            tracker = Tracker(dataset, scene_id, frames, config, track, problem_config, workers, split, object_ids,
                              early_stop, max_retries)
            try:
                count += len(track_frames(tracker, frames, done.get(scene_id, set()), on_frame))
            finally:
                tracker.close()
        return count

    def finished(unit: tuple, results: list[FrameResult]) -> None:
        nonlocal count
        for result in results:
            tqdm.write(result.line, file=sys.stderr)  # above the sequences' bar
            on_frame(result)
        count += len(results)

    units = [(scene_id, frames, done.get(scene_id, set())) for scene_id, frames in sequences.items()]
    shared = (Path(dataset).resolve(), config, track, problem_config, workers, split, object_ids, early_stop)
    run_ray_tasks(track_sequence_task, units, shared, ray, finished, on_failure, "sequences", "sequence",
                  lambda unit: ((unit[0], unit[1][0]), f"scene {unit[0]}"))
    return count
