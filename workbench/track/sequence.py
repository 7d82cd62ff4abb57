"""The frame loop of ``workbench track``: one scene's frames in id order, the first estimated as ``estimate`` does,
each next one tracked from the previous one (``Tracker.step``), with its status in words.

``Tracker.resume`` and ``Tracker.advance`` are the same loop driven from outside, one frame at a time: the workbench
tracks the next frame from the run it shows, with its own evaluator (``evaluator_for``).

The frames share one table frame: the first frame's (found in its depth, or given), moved by the camera's motion
from frame to frame (``motion``) and kept by the support fit when the depth agrees with it (``support``). Objects
that do not move therefore keep their table-frame poses, and the previous frame's particles, estimate, candidates
and posterior (``track_search.Carried``) are the next frame's prior as they are. One evaluator serves the whole
sequence, given each frame's problem in turn (``retarget``): no worker processes started per frame.
"""

from __future__ import annotations

import contextlib
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from workbench.errors import InputError
from workbench.evaluation import Evaluator, WorkerCrashed, make_evaluator
from workbench.geometry import invert_pose
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator, object_confidence
from workbench.inference.search.geometry import SearchGeometry
from workbench.inference.search.scenepoints import object_badness
from workbench.inference.search.track_search import Carried, TrackSearch
from workbench.io import bop
from workbench.io.results import ResultRow, posterior_rows, result_rows
from workbench.meshes.heavy import announced
from workbench.problem.build import problem_for_frame
from workbench.problem.problem import Problem, ProblemConfig
from workbench.problem.scene import Frame
from workbench.run.runner import estimator_rows, run_estimator
from workbench.track.config import TrackConfig
from workbench.track.frames import sequence_world
from workbench.track.lost import NO_DEPTH, RECOVERED, lost_objects, status_words
from workbench.track.motion import depth_motion, given_motion


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


@dataclass(frozen=True)
class TrackedFrame:
    """A frame as ``Tracker.advance`` left it: the ``frame`` and its ``problem`` in the sequence's table frame, the
    finished ``estimator`` and its answer ``best`` (K, 4, 4), table frame; ``status`` and ``motion`` as
    ``FrameResult``'s."""

    frame: Frame
    problem: Problem
    estimator: Estimator
    best: np.ndarray
    status: str
    motion: str
    lost: np.ndarray | None = None  # (K,) bool: objects lost and not found again (held where last found)


def carry(estimator: Estimator, best: np.ndarray) -> Carried:
    """What a finished frame hands the next (``Carried``): its particles, estimate, answer, sink, candidates,
    posterior, search geometry, and how badly each object of its answer ``best`` (K, 4, 4) explains that frame."""
    problem, search, f = estimator.problem, estimator.search, estimator.filter
    geometry = (search.geometry(f) if hasattr(search, "geometry")
                else SearchGeometry.of(problem, upright=estimator.config.state == "xyzyaw"))
    return Carried(particles=estimator.particles.projected.copy(), weights=estimator.weights(),
                   estimate=(best if f.estimate is None else f.estimate).copy(), settled=best.copy(), sink=f.sink,
                   library=getattr(search, "library", None), posterior=estimator.posterior, geometry=geometry,
                   badness=object_badness(problem, best, geometry.samples))


class Tracker:
    """One scene's ``frames`` (image ids), stepped in order (``step``); ``restart`` makes the next frame start from
    scratch.
    ``config``: the first (and any re-initialised) frame's estimator settings, as ``estimate``'s; ``track``: the
    tracked frames'. ``evaluator_for(problem)``: the evaluator of each frame's problem; by default one of
    ``workers`` processes, started with the first frame and given each next one's problem (``close`` ends it)."""

    def __init__(self, dataset: Path, scene_id: int, frames: list[int], config: EstimatorConfig,
                 track: TrackConfig, problem_config: ProblemConfig = ProblemConfig(), workers: int = 2,
                 split: str | None = None, object_ids: list[int] | None = None, early_stop: bool = True,
                 max_retries: int = 3, evaluator_for: Callable[[Problem], Evaluator] | None = None):
        track.validate()
        self.dataset, self.scene_id, self.split, self.object_ids = Path(dataset), scene_id, split, object_ids
        self.config, self.track, self.problem_config = config, track, problem_config
        self.workers, self.early_stop, self.max_retries = workers, early_stop, max_retries
        self.world = sequence_world(self.dataset, scene_id, split, track.motion, frames)
        self.evaluator = None
        self._serving: Problem | None = None  # the problem ``evaluator`` was last given
        self.evaluator_for = evaluator_for
        self.models: dict = {}
        self._light: dict[int, tuple] = {}  # id of a model's mesh -> (it, the model with its light copy; _sent)
        self.previous: tuple[Frame, Problem] | None = None
        self.carried: Carried | None = None
        self._started: Carried | None = None  # the carried state the frame being tracked started from
        self.after_gap = False  # the frame before was lost (no depth)

    def restart(self) -> None:
        self.carried = self.previous = self._started = None
        self.after_gap = False

    def close(self) -> None:
        if self.evaluator is not None:
            self.evaluator.close()
            self.evaluator = self._serving = None

    def step(self, im_id: int) -> FrameResult:
        """Estimate or track frame ``im_id`` (the one after the previous step's, unless restarted). A frame without
        depth (``TrackConfig.min_depth_share``) is lost as a whole (``lost.NO_DEPTH``): the posterior carried through
        it unchanged, its rows the carried answer where the camera now is; the next frame is tracked from the last
        one with depth, and says it has ``lost.RECOVERED``."""
        t0 = time.perf_counter()
        if self._without_depth(im_id):
            return self._lost_frame(im_id, t0)
        # A frame estimated from scratch takes 10-60 s, with lines only at the end of its steps: said while it goes.
        with (announced(f"estimating scene {self.scene_id} frame {im_id} from scratch", cached=False)
              if self.carried is None else contextlib.nullcontext()):
            done = self.advance(im_id)
        if self.after_gap and done.status not in ("estimated", "re-initialised"):
            done = replace(done, status=RECOVERED if done.status == "tracked" else f"{RECOVERED}, {done.status}")
        self.after_gap = False
        seconds = time.perf_counter() - t0
        rows = estimator_rows(done.frame, done.problem, done.estimator, done.best, seconds)
        self.resume(done.frame, done.problem, done.estimator, done.best, done.lost)
        how = f" (camera motion {done.motion})" if done.motion else ""
        line = f"scene {self.scene_id} frame {im_id}: {done.status} in {seconds:.1f} s{how}"
        if done.estimator.posterior is not None:
            line += f"; {done.estimator.posterior.summary(done.problem)}"
        return FrameResult(rows, done.status, seconds, done.motion, line)

    def resume(self, frame: Frame, problem: Problem, estimator: Estimator, best: np.ndarray,
               lost: np.ndarray | None = None) -> None:
        """The next frame starts from ``frame`` (its ``problem``) as ``estimator`` finished it, ``best`` (K, 4, 4)
        its answer: the last frame ``advance`` gave, or one estimated elsewhere (the workbench's run). ``lost``
        (K,) bool: objects that frame lost and did not find again, held where the frame before had them."""
        carried = carry(estimator, best)
        if lost is not None and self._started is not None:
            carried = carried.held(self._started, lost)
        self.carried, self.previous, self._started = carried, (frame, problem), None
        self.models.update({m.obj_id: m for m in problem.models})

    def advance(self, im_id: int) -> TrackedFrame:
        """Estimate frame ``im_id`` from scratch, or track it from the frame the tracker ``resume``s from (unless
        restarted) -> what it became. A frame that cannot be read fails (InputError) before any evaluator is used."""
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
            self._started = carried
            estimator, best, status, lost = self._track(problem, carried)
            return TrackedFrame(frame, problem, estimator, best, status, motion, lost)
        return TrackedFrame(frame, problem, estimator, best, status, motion)

    # ----------------------------------------------------------------------------------------------------- parts
    def _use(self, problem: Problem) -> Evaluator:
        """The evaluator, for ``problem``: ``evaluator_for``'s, or one started with the first frame and given each
        next frame's problem (once: a frame re-initialised after its lost check asks again)."""
        if self.evaluator_for is not None:
            return self.evaluator_for(problem)
        if problem is self._serving:
            return self.evaluator
        sent = self._sent(problem)
        try:
            if self.evaluator is None:
                self.evaluator = make_evaluator(sent, self.workers, max_retries=self.max_retries)
            else:
                self.evaluator.retarget(sent)
        except WorkerCrashed as err:
            raise InputError(f"scene {self.scene_id}", f"{err}; the frames before it are kept (run again with "
                                                       "--resume)") from None
        self._serving = problem
        return self.evaluator

    def _sent(self, problem: Problem) -> Problem:
        """``problem`` as the evaluator's workers get it, each frame: its models' meshes without what trimesh
        caches on them (6 MB a YCB-Video model, 35 MB for scene 2's six; 0.6 MB each without), the same vertices
        and faces, so the same collision shapes and render meshes (cached by their content). Sending the cached
        ones cost about 0.3 s of every tracked frame."""
        models = []
        for m in problem.models:
            if id(m.mesh) not in self._light:  # the mesh itself kept, so that its id is not reused
                light = trimesh.Trimesh(vertices=m.mesh.vertices, faces=m.mesh.faces, process=False)
                self._light[id(m.mesh)] = (m.mesh, replace(m, mesh=light))
            models.append(self._light[id(m.mesh)][1])
        return replace(problem, models=models)

    def _estimate(self, problem: Problem, desc: str) -> tuple[Estimator, np.ndarray]:
        """From scratch, as ``estimate`` does: its posterior's open ranges of headings are modes every
        ``posterior.RANGE_STEP_DEG``, for the frames after it to decide among."""
        return run_estimator(Estimator(problem, self.config, self._use(problem)), desc, self.early_stop,
                             show_progress=True)

    def _tracked_problem(self, frame: Frame) -> tuple[Frame, Problem, Carried]:
        """The frame in the sequence's table frame (the previous frame's, moved by the camera's motion), its
        problem, and the carried state in the table frame the support fit kept (the same, unless the depth
        contradicted it and the table was found anew)."""
        previous, prev_problem = self.previous
        if self.world is not None:
            M = given_motion(self.world[previous.im_id], self.world[frame.im_id])
        else:
            t = prev_problem.table
            M = depth_motion(previous, frame, prev_problem.camera.T_cam_world, (t.region_min, t.region_max))
        expected = M @ prev_problem.camera.T_cam_world
        table_carried = frame.camera.T_cam_world is None  # a table pose the dataset gives is the same table's: kept
        if table_carried:  # the support the frame before found, raised support and all: not looked for again
            frame = replace(frame, camera=frame.camera.with_pose(expected))
        problem = problem_for_frame(frame, self.models, self.problem_config, raised=not table_carried)
        return frame, problem, self.carried.moved(invert_pose(problem.camera.T_cam_world) @ expected)

    def _track(self, problem: Problem, carried: Carried) -> tuple[Estimator, np.ndarray, str, np.ndarray | None]:
        """The short search from the carried state; objects it no longer explains re-searched, the frame
        estimated from scratch when most are -> (the estimator, its answer, the status, the objects still lost
        (K,) bool, or None when re-initialised)."""
        t = self.track
        evaluator = self._use(problem)  # the workers build the frame's physics and renderer while this goes on
        samples = carried.geometry.samples
        lost = lost_objects(object_badness(problem, carried.settled, samples), carried.badness, t.lost_badness,
                            t.lost_rise)
        if lost.sum() > t.reinit_share * problem.n_objects:
            return *self._estimate(problem, f"scene {self.scene_id}: re-initialising"), "re-initialised", None
        search = TrackSearch(problem, carried, np.flatnonzero(lost).tolist())
        estimator = Estimator(problem, t.frame_config(self.config, bool(lost.any())), evaluator, search)
        _, best = run_estimator(estimator, "tracking", early_stop=False)
        still = lost & lost_objects(object_badness(problem, best, samples), carried.badness, t.lost_badness,
                                    t.lost_rise)
        recovered = 0 if carried.lost is None else int((carried.lost & ~lost).sum())
        return estimator, best, status_words(int(lost.sum()), int((lost & ~still).sum()), recovered), still

    def _without_depth(self, im_id: int) -> bool:
        """Whether frame ``im_id``'s depth has readings on less than ``TrackConfig.min_depth_share`` of its pixels
        (a dropped or blanked frame)."""
        path = bop.scene_folder(self.dataset, self.scene_id, self.split) / "depth" / f"{im_id:06d}.png"
        return float(np.mean(bop.read_depth_png(path) > 0)) < self.track.min_depth_share

    def _lost_frame(self, im_id: int, t0: float) -> FrameResult:
        """A frame without depth: nothing to search. The carried answer and posterior as they are, in the camera
        where the given motion puts it (without one, where it was: there is no depth to register), as its rows;
        the carried state is left as it was, for the next frame with depth (tracked from the last one)."""
        self.after_gap = True
        if self.carried is None:  # nothing carried yet: nothing to report, the next frame is estimated
            seconds = time.perf_counter() - t0
            return FrameResult([], NO_DEPTH, seconds, "", f"scene {self.scene_id} frame {im_id}: {NO_DEPTH} in "
                                                          f"{seconds:.1f} s; nothing carried yet")
        previous, prev_problem = self.previous
        T_cam_world = prev_problem.camera.T_cam_world
        if self.world is not None:
            T_cam_world = given_motion(self.world[previous.im_id], self.world[im_id]) @ T_cam_world
        problem = replace(prev_problem, camera=prev_problem.camera.with_pose(T_cam_world))
        frame = replace(previous, im_id=im_id, camera=problem.camera, gt_T_cam_obj=None, rgb=None)
        c = self.carried
        seconds = time.perf_counter() - t0
        if c.posterior is not None:
            rows = posterior_rows(frame, problem, c.posterior, seconds)
        else:
            rows = result_rows(frame, problem, c.settled, object_confidence(problem, c.particles, c.weights, c.settled),
                               seconds)
        motion = "given" if self.world is not None else ""
        line = f"scene {self.scene_id} frame {im_id}: {NO_DEPTH} in {seconds:.1f} s (camera motion " \
               f"{motion or 'unknown, taken as still'}); the last answer carried"
        return FrameResult(rows, NO_DEPTH, seconds, motion, line)


def track_frames(tracker: Tracker, frames: list[int], done: set[int],
                 on_frame: Callable[[FrameResult], None], echo: bool = True) -> list[FrameResult]:
    """Step ``tracker`` over ``frames`` (image ids in order). Each frame's result goes to ``on_frame`` as soon as it
    is done, and (``echo``) its line to stderr, but for those in ``done`` (a resumed run's, already written): they
    are tracked again, unwritten, because each frame starts from the one before, so that the frames after them get
    the rows an undisturbed run gives."""
    results = []
    for im_id in frames:
        result = tracker.step(im_id)
        if im_id in done:
            if echo:
                print(f"scene {tracker.scene_id} frame {im_id}: kept from before; tracked again in "
                      f"{result.seconds:.1f} s to carry on from it", file=sys.stderr)
            continue
        if echo:
            print(result.line, file=sys.stderr)
        on_frame(result)
        results.append(result)
    return results
