"""The frame loop of `estimate` and `bench`: dataset frames run here one after another (``--engine local``) or as
Ray tasks over a cluster (``--engine ray``), each frame's result handed to a callback as soon as it is done.

Results do not depend on the engine: a frame task evaluates its batches with a ``ChunkedEvaluator`` (the batch split
as ``--workers`` local processes would split it, evaluated in turn on the task's one CPU), and the estimator's seed
is the config's, the same for every frame whatever ran it and in whatever order. So a run with `--engine ray` writes
the same poses and scores as one with `--engine local` and the same ``--workers`` (only the time column differs).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Callable, TypeVar

from tqdm import tqdm

from workbench.errors import InputError
from workbench.evaluation.ray import RayConfig, connect  # imports Ray only when used

FrameKey = tuple[int, int]  # (scene_id, im_id): which frame, not the loaded one (problem.scene.Frame)
Result = TypeVar("Result")


@dataclass(frozen=True)
class FrameFailure:
    """A frame that produced no result: ``problem`` says why in words (its input error, or its worker dying more
    often than ``RayConfig.max_retries`` allows)."""

    frame: FrameKey
    problem: str


def _frame_problem(ray, err: Exception, retries: int) -> str:
    if isinstance(err, ray.exceptions.RayTaskError):
        cause = err.cause if getattr(err, "cause", None) is not None else err
        return str(cause) if isinstance(cause, InputError) else f"{type(cause).__name__}: {cause}"
    if isinstance(err, (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError,
                        ray.exceptions.ObjectLostError, ray.exceptions.OwnerDiedError)):
        return f"its worker died {retries + 1} time(s) ({type(err).__name__}); gave up"
    return f"{type(err).__name__}: {err}"


def run_frames(
    frames: list[FrameKey],
    here: Callable[[int, int], Result],
    task: Callable[..., Result],
    args: tuple,
    ray: RayConfig | None,
    on_result: Callable[[FrameKey, Result], None],
    on_failure: Callable[[FrameFailure], None],
    desc: str = "frames",
) -> None:
    """Run every frame and hand each result to ``on_result(frame, result)`` as soon as it is done.

    Locally (``ray`` None): ``here(scene_id, im_id)``, one frame after another in the order given, in this process
    (which shows its own progress); the first frame that raises ends the run with its error.

    With ``ray`` (a RayConfig): ``task(scene_id, im_id, *args)`` for every frame as a Ray task of one CPU, as many at
    once as the cluster has CPUs, results in the order the tasks finish; each frame that failed goes to
    ``on_failure`` and the others go on. One progress bar on stderr, named ``desc``, counts finished frames.
    ``task`` must be a module-level function (workers import it by name); ``args`` are put into Ray's object store
    once, not once per frame."""
    if ray is None:
        for frame in frames:
            on_result(frame, here(*frame))
    else:
        run_ray_tasks(task, frames, args, ray, on_result, on_failure, desc, "frame",
                      lambda frame: (frame, f"scene {frame[0]} frame {frame[1]}"))


def run_ray_tasks(task: Callable[..., Result], units: list[tuple], args: tuple, config: RayConfig,
                  on_result: Callable[[tuple, Result], None], on_failure: Callable[[FrameFailure], None], desc: str,
                  unit: str, named: Callable[[tuple], tuple[FrameKey, str]]) -> None:
    """``task(*unit, *args)`` for every unit of work (a tuple of its own arguments: a frame's (scene_id, im_id), a
    sequence's scene and frames) as a Ray task of one CPU, as many at once as the cluster has CPUs; each result to
    ``on_result(unit, result)`` in the order the tasks finish, each unit that failed to ``on_failure`` (as the
    ``FrameFailure`` of the frame ``named(unit)`` gives, with the name its line says) while the others go on. One
    progress bar on stderr counts finished units; ``args`` are put into Ray's object store once."""
    ray = connect(config)
    # Worker processes are reused across tasks (Ray's default), so each imports the heavy libraries once.
    remote = ray.remote(num_cpus=1, max_retries=config.max_retries, retry_exceptions=False)(task)
    shared = [ray.put(a) for a in args]
    pending = {remote.remote(*u, *shared): u for u in units}
    with tqdm(total=len(units), desc=desc, unit=unit, file=sys.stderr, disable=None) as bar:  # terminals only
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            u = pending.pop(done[0])
            try:
                result = ray.get(done[0])
            except ray.exceptions.RayError as err:
                frame, name = named(u)
                failure = FrameFailure(frame, _frame_problem(ray, err, config.max_retries))
                bar.write(f"workbench: {name} failed: {failure.problem}", file=sys.stderr)
                on_failure(failure)
            else:
                on_result(u, result)
            bar.update(1)
