"""The frame loop of ``workbench track``: one scene's frames in id order, the first estimated as ``estimate`` does,
each next one tracked from the previous one (``Tracker.step``), with its status in words.

The frames share one table frame: the first frame's (found in its depth, or given), moved by the camera's motion
from frame to frame (``motion``) and kept by the support fit when the depth agrees with it (``support``). Objects
that do not move therefore keep their table-frame poses, and the previous frame's particles, estimate, candidates
and posterior (``track_search.Carried``) are the next frame's prior as they are. One evaluator serves the whole
sequence, given each frame's problem in turn (``retarget``): no worker processes started per frame.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from workbench.errors import InputError
from workbench.estimators import Estimator
from workbench.evaluation import WorkerCrashed, make_evaluator
from workbench.geometry import invert_pose
from workbench.inference.config import EstimatorConfig
from workbench.inference.context import SearchGeometry
from workbench.inference.scenepoints import object_badness
from workbench.inference.track_search import Carried, TrackSearch
from workbench.io import bop
from workbench.io.bop import ResultRow
from workbench.pipeline import problem_for_frame
from workbench.problem import Problem, ProblemConfig
from workbench.runner import estimator_rows, run_estimator
from workbench.scene import Frame
from workbench.track import lost as lost_words
from workbench.track.config import TrackConfig
from workbench.track.motion import WORLD_FILE, depth_motion, given_motion, read_world_poses


@dataclass(frozen=True)
class FrameResult:
    """One frame's BOP result rows (``time`` its wall ``seconds``), its ``status`` in words ("estimated",
    "tracked", "2 objects re-found", "re-initialised") and where the camera's motion came from (``motion``:
    "given", "depth", or "" on a frame estimated from scratch)."""

    rows: list[ResultRow]
    status: str
    seconds: float
    motion: str
    line: str  # the frame's line on stderr


def carry(estimator: Estimator, best: np.ndarray) -> Carried:
    """What a finished frame hands the next (``Carried``): its particles, estimate, answer, sink, candidates,
    posterior, search geometry, and how badly each object of its answer ``best`` (K, 4, 4) explains that frame."""
    problem, search, f = estimator.problem, estimator.search, estimator.filter
    geometry = (search.geometry(f) if hasattr(search, "geometry")
                else SearchGeometry.of(problem, upright=estimator.config.state == "xyzyaw"))
    return Carried(particles=estimator.particles.projected.copy(), weights=estimator.weights(),
                   estimate=(best if f.map is None else f.map).copy(), settled=best.copy(), sink=f.sink,
                   library=getattr(search, "library", None), posterior=estimator.posterior, geometry=geometry,
                   badness=object_badness(problem, best, geometry.samples))


class Tracker:
    """One scene's ``frames`` (image ids), stepped in order (``step``); ``restart`` makes the next frame start from
    scratch.
    ``config``: the first (and any re-initialised) frame's estimator settings, as ``estimate``'s; ``track``: the
    tracked frames'. ``close`` ends the evaluator's worker processes."""

    def __init__(self, dataset: Path, scene_id: int, frames: list[int], config: EstimatorConfig,
                 track: TrackConfig, problem_config: ProblemConfig = ProblemConfig(), workers: int = 2,
                 split: str | None = None, object_ids: list[int] | None = None, early_stop: bool = True,
                 max_retries: int = 3):
        track.validate()
        self.dataset, self.scene_id, self.split, self.object_ids = Path(dataset), scene_id, split, object_ids
        self.config, self.track, self.problem_config = config, track, problem_config
        self.workers, self.early_stop, self.max_retries = workers, early_stop, max_retries
        self.world = world_poses(self.dataset, scene_id, split, track.motion)
        check_world_poses(self.world, frames, bop.scene_folder(self.dataset, scene_id, split) / WORLD_FILE)
        self.evaluator = None
        self.models: dict = {}
        self.previous: tuple[Frame, Problem] | None = None
        self.carried: Carried | None = None

    def restart(self) -> None:
        self.carried = self.previous = None

    def close(self) -> None:
        if self.evaluator is not None:
            self.evaluator.close()
            self.evaluator = None

    def step(self, im_id: int) -> FrameResult:
        """Estimate or track frame ``im_id`` (the one after the previous step's, unless restarted)."""
        t0 = time.perf_counter()
        frame = bop.load_frame(self.dataset, self.scene_id, im_id, self.split, self.object_ids)
        missing = sorted(set(frame.object_ids) - set(self.models))
        if missing:
            self.models.update(bop.load_models(self.dataset, missing))
        if self.previous is not None and self.previous[0].object_ids != frame.object_ids:
            self.restart()  # another set of objects: nothing to carry
        motion = ""
        if self.carried is None:
            problem = problem_for_frame(frame, self.models, self.problem_config)
            estimator, best, status = *self._estimate(problem, f"scene {self.scene_id} frame {im_id}"), "estimated"
        else:
            motion = "given" if self.world is not None else "depth"
            frame, problem, carried = self._tracked_problem(frame)
            estimator, best, status = self._track(problem, carried)
        seconds = time.perf_counter() - t0
        rows = estimator_rows(frame, problem, estimator, best, seconds)
        self.carried, self.previous = carry(estimator, best), (frame, problem)
        how = f" (camera motion {motion})" if motion else ""
        line = f"scene {self.scene_id} frame {im_id}: {status} in {seconds:.1f} s{how}"
        if estimator.posterior is not None:
            line += f"; {estimator.posterior.summary(problem)}"
        return FrameResult(rows, status, seconds, motion, line)

    # ----------------------------------------------------------------------------------------------------- parts
    def _use(self, problem: Problem) -> None:
        """The evaluator, for ``problem``: started with the first frame, given each next frame's problem."""
        try:
            if self.evaluator is None:
                self.evaluator = make_evaluator(problem, self.workers, max_retries=self.max_retries)
            else:
                self.evaluator.retarget(problem)
        except WorkerCrashed as err:
            raise InputError(f"scene {self.scene_id}", f"{err}; the frames before it are kept (run again with "
                                                       "--resume)") from None

    def _estimate(self, problem: Problem, desc: str) -> tuple[Estimator, np.ndarray]:
        """From scratch, as ``estimate`` does."""
        self._use(problem)
        return run_estimator(Estimator(problem, self.config, self.evaluator), desc, self.early_stop,
                             show_progress=True)

    def _tracked_problem(self, frame: Frame) -> tuple[Frame, Problem, Carried]:
        """The frame in the sequence's table frame (the previous frame's, moved by the camera's motion), its
        problem, and the carried state in the table frame the support fit kept (the same, unless the depth
        contradicted it and the table was found anew)."""
        previous, prev_problem = self.previous
        if self.world is not None:
            M = given_motion(self.world[previous.im_id], self.world[frame.im_id])
        else:
            M = depth_motion(previous, frame)
        expected = M @ prev_problem.camera.T_cam_world
        if frame.camera.T_cam_world is None:  # a table pose the dataset gives is the same table's: kept
            frame = replace(frame, camera=frame.camera.with_pose(expected))
        problem = problem_for_frame(frame, self.models, self.problem_config)
        return frame, problem, self.carried.moved(invert_pose(problem.camera.T_cam_world) @ expected)

    def _track(self, problem: Problem, carried: Carried) -> tuple[Estimator, np.ndarray, str]:
        """The short search from the carried state; objects it no longer explains re-searched, the frame
        estimated from scratch when most are."""
        t = self.track
        samples = carried.geometry.samples
        lost = lost_words.lost_objects(object_badness(problem, carried.settled, samples), carried.badness,
                                       t.lost_badness, t.lost_rise)
        if lost.sum() > t.reinit_share * problem.n_objects:
            return *self._estimate(problem, f"scene {self.scene_id}: re-initialising"), "re-initialised"
        self._use(problem)
        search = TrackSearch(problem, carried, np.flatnonzero(lost).tolist())
        estimator = Estimator(problem, t.frame_config(self.config, bool(lost.any())), self.evaluator, search)
        _, best = run_estimator(estimator, "tracking", early_stop=False)
        still = lost_words.lost_objects(object_badness(problem, best, samples), carried.badness, t.lost_badness,
                                        t.lost_rise)
        return estimator, best, lost_words.status(int(lost.sum()), int((lost & ~still).sum()))


def world_poses(dataset: Path, scene_id: int, split: str | None, motion: str) -> dict[int, np.ndarray] | None:
    """The scene's camera poses for ``motion`` "given" (InputError when the scene has none) or "auto" (None
    without the file: the motion is registered from the depth); None for "depth"."""
    if motion == "depth":
        return None
    folder = bop.scene_folder(dataset, scene_id, split)
    poses = read_world_poses(folder)
    if poses is None and motion == "given":
        raise InputError(folder / WORLD_FILE, "not found: --motion given needs each frame's camera pose in the world "
                                              "frame (R_w2c, t_w2c mm); use --motion depth to register the camera's "
                                              "motion from the depth instead")
    return poses


def sequence_frames(dataset: Path, scene_id: int, split: str | None, frames: str | None) -> list[int]:
    """The image ids of ``--frames A:B`` (both included; default: all) of one scene, in order. InputError when the
    scene, A or B is not there, when an id between them is missing (a sequence needs every frame) or a frame's
    depth image is."""
    folder = bop.scene_folder(dataset, scene_id, split)
    cam_path = folder / "scene_camera.json"
    ids = sorted(bop.image_ids(bop.read_json(cam_path), cam_path))
    if not ids:
        raise InputError(cam_path, "lists no frames")
    lo, hi = ids[0], ids[-1]
    if frames is not None:
        try:
            lo, hi = (int(v) for v in frames.split(":"))
        except ValueError:
            raise InputError("--frames", f"must be A:B, two image ids (e.g. 1:20), got {frames!r}") from None
        if lo > hi:
            raise InputError("--frames", f"A:B must have A <= B, got {frames}")
        for v in (lo, hi):
            if v not in ids:
                raise InputError("--frames", f"scene {scene_id} has no frame {v} (frames {ids[0]}..{ids[-1]}, "
                                             f"{len(ids)} of them, in {cam_path})")
    chosen = [i for i in ids if lo <= i <= hi]
    gaps = sorted(set(range(lo, hi + 1)) - set(chosen))
    if gaps:
        raise InputError(cam_path, f"frame {gaps[0]} is missing between {lo} and {hi}: a sequence needs every frame; "
                                   f"track the parts either side of it (--frames)")
    for i in chosen:
        if not (folder / "depth" / f"{i:06d}.png").is_file():
            raise InputError(folder / "depth" / f"{i:06d}.png", f"not found: frame {i} of the sequence has no depth")
    return chosen


def check_world_poses(world: dict[int, np.ndarray] | None, frames: list[int], path: Path) -> None:
    """Every frame of the sequence has its camera pose in ``world`` (when there is one): InputError naming
    ``path`` and the first frame without one."""
    if world is not None:
        lacking = [i for i in frames if i not in world]
        if lacking:
            raise InputError(path, f"frame {lacking[0]} has no camera pose (R_w2c, t_w2c); the sequence needs one "
                                   "for every frame (or use --motion depth)")


def track_frames(tracker: Tracker, frames: list[int], done: set[int],
                 on_frame: Callable[[FrameResult], None]) -> list[FrameResult]:
    """Step ``tracker`` over ``frames`` (image ids in order), skipping those in ``done`` (a resumed run's): the
    frame after a skipped one starts from scratch. Each frame's result goes to ``on_frame`` as soon as it is done,
    and its line to stderr."""
    results = []
    for im_id in frames:
        if im_id in done:
            tracker.restart()
            continue
        result = tracker.step(im_id)
        print(result.line, file=sys.stderr)
        on_frame(result)
        results.append(result)
    return results
