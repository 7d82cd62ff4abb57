"""Sequences on the engine's side: the loaded frame's scene, frame after frame, as ``workbench track`` runs it.

Loading a frame of a scene with several frames starts a sequence at it. *Next frame* tracks the scene's next frame
from the run on show (``track.sequence.Tracker``: ``resume`` from that run, ``advance`` to the next frame, with the
engine's evaluator given the new frame's problem); the first frame, and a frame most of whose objects are lost, run
with the panel's settings, as ``workbench track``'s ``--particles`` and ``--iterations``. Every processed frame
keeps its frame, problem, view and run, so that the timeline shows any of them again without re-running it.

Next from a frame shown again: where its run is as it was when its next frame was tracked from it, Next shows that
next frame as it was (stepping along the timeline); where the user changed the run (stepped, reset), Next tracks
the next frame from it anew and the frames processed after it are dropped: they followed from the old run.

Bad input (Next on the scene's last frame, a next frame without depth, too few depth readings to register the
camera's motion) is reported before anything changes: the frame on show and its run stay as they were.
"""

from __future__ import annotations

import logging
import time
import traceback
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from workbench.app import protocol as p
from workbench.app.engine.on_show import RunOnShow
from workbench.app.ui.run.truth import top_probabilities
from workbench.errors import InputError
from workbench.sessions.sequence_record import SequenceRecord

log = logging.getLogger(__name__)

# The first frame's status on the timeline: before its run has an iteration, then once it has (it is the frame
# estimated from scratch; the frames after it say how they were tracked).
NOT_RUN, ESTIMATED = "not run yet", "estimated"


@dataclass
class HeldRun:
    """What shows a processed frame again: ``source`` (what a restarted engine reloads), ``view``, ``frame``,
    ``problem`` (in the sequence's table frame) and its run, ``estimator``."""

    source: p.Source
    view: p.ObservationView
    frame: object  # scene.Frame
    problem: object  # problem.Problem
    estimator: object  # estimators.Estimator


@dataclass
class Processed:
    """One processed frame: its timeline ``entry``; its ``held`` run (None: not in the session it was restored
    from); ``handed``: the run and its iteration the next frame was tracked from (None: not yet)."""

    entry: p.SequenceFrame
    held: HeldRun | None
    handed: tuple[object, int] | None = None


def told(results, action: Callable[[], object], topic: str, not_done: str, failed: str) -> object:
    """Do ``action`` -> what it returns; where it fails, None, and the failure is told under ``topic`` (beside that
    part's buttons): bad input as it is, titled ``not_done``; anything else titled ``failed`` with its type, and
    logged. The run on show goes on either way: a failed Next, check or fit must leave it usable."""
    try:
        return action()
    except InputError as err:
        results.put(p.Failure(not_done, err.problem, err.path, topic=topic))
    except Exception as err:  # noqa: BLE001 - see the docstring
        log.error("%s error\n%s", topic, traceback.format_exc())
        results.put(p.Failure(f"{failed} ({type(err).__name__})", str(err) or repr(err), topic=topic))
    return None


def scene_frame_ids(dataset: Path, scene_id: int, split: str | None) -> tuple[int, ...]:
    """The image ids of the scene's ``scene_camera.json``, in order."""
    from workbench.io import bop, readers

    path = bop.scene_folder(dataset, scene_id, split) / "scene_camera.json"
    return tuple(sorted(bop.image_ids(readers.read_json(path), path)))


def run_summary(estimator) -> tuple[np.ndarray, np.ndarray]:
    """A run's answer for the plots across frames -> (positions (K, 3) m, table frame: the settled answer where it
    is the current estimate's, else the best scene, NaN before the first iteration; (K,) each object's top mode's
    probability, NaN without a posterior)."""
    K = estimator.problem.n_objects
    if estimator.iteration < 0:
        return np.full((K, 3), np.nan), np.full(K, np.nan)
    scene = estimator.settled if estimator.answer_current else estimator.estimate
    return np.array(scene[:, :3, 3], dtype=np.float64), np.array(top_probabilities(estimator.current_posterior, K))


class EngineSequence:
    """The sequence of the frame on show, or none (``scene_id`` None: the frame's scene has one frame, or it is not
    a dataset's). Given only what it uses of the engine: ``results`` (what the server is told), the ``evaluators``
    (the pool a tracked frame is evaluated on), ``on_show`` (-> the run on show, read-only) and ``pause`` (stops a
    Run, telling the server). It changes nothing of the engine's: Next and a jump return the ``HeldRun`` to put on
    show, and the engine puts it there (``Engine.put_on_show``)."""

    def __init__(self, results, evaluators, on_show: Callable[[], RunOnShow], pause: Callable[[], None]):
        self.results = results
        self.evaluators = evaluators
        self.on_show = on_show
        self.pause = pause
        self.scene_id: int | None = None
        self.dataset: Path | None = None  # as the frames are loaded from it (the root with ``split``, or a split)
        self.split: str | None = None
        self.frame_ids: tuple[int, ...] = ()
        self.frames: list[Processed] = []
        self.at = 0  # the index in ``frames`` of the frame on show

    # -- starting

    def start(self, source: p.Source, dataset: Path, split: str | None, view: p.ObservationView,
              record: SequenceRecord | None = None) -> None:
        """The engine loaded a frame (from a session with its ``record``, or none): a sequence at it where its
        scene has more frames, else none. Tells the server either way."""
        e = self.on_show()
        self.scene_id, self.frames, self.at = None, [], 0
        try:
            ids = scene_frame_ids(dataset, e.frame.scene_id, split)
        except InputError:  # the frame came from elsewhere than a scene folder: no sequence to offer
            ids = ()
        if len(ids) > 1:
            self.scene_id, self.dataset, self.split, self.frame_ids = e.frame.scene_id, Path(dataset), split, ids
            held = HeldRun(source, view, e.frame, e.problem, e.estimator)
            if record is None:
                self.frames = [Processed(p.SequenceFrame(e.frame.im_id, NOT_RUN, 0.0, "",
                                                         *run_summary(e.estimator)), held)]
            else:
                self.frames = [Processed(f, None) for f in record.frames]
                self.at = [f.im_id for f in record.frames].index(record.current)
                self.frames[self.at].held = held
        self.publish(reports=[r.as_dict() for r in e.estimator.history] if record is not None else None)

    # -- commands

    def guarded(self, action: Callable[[], None]) -> None:
        """Next or a jump: whatever fails is told beside the sequence's buttons; the frame on show stays."""
        told(self.results, action, "sequence", "Sequence: not done", "Next frame failed")

    def next(self) -> HeldRun:
        """Go to the scene's frame after the one on show (module docstring) -> its run, to put on show."""
        from workbench.app.engine.observation import build_view
        from workbench.track.config import TrackConfig
        from workbench.track.sequence import Tracker

        e, here = self.on_show(), self.here()
        est, nxt = e.estimator, self.next_id()
        if nxt is None:
            raise InputError("Next frame", f"frame {here.entry.im_id} is the last of scene {self.scene_id} (frames "
                                           f"{self.frame_ids[0]}..{self.frame_ids[-1]}): there is no next frame")
        if est is None or est.iteration < 0:
            raise InputError("Next frame", f"frame {here.entry.im_id} has no run to track from yet: press Step or Run "
                                           "first (the next frame starts from its particles)")
        if self.at + 1 < len(self.frames) and here.handed is not None and here.handed[0] is est \
                and here.handed[1] == est.iteration:
            return self.show(nxt)
        self.pause()  # Next during a Run: the run stops where it is, and is tracked from there
        tracker = Tracker(self.dataset, self.scene_id, [here.entry.im_id, nxt], e.config, TrackConfig(),
                          e.problem.config, split=self.split, early_stop=e.stop_on_convergence,
                          evaluator_for=self.evaluators.retarget)
        tracker.resume(e.frame, e.problem, est, est.settle())
        t0 = time.perf_counter()
        try:
            done = tracker.advance(nxt)
        except BaseException:
            self.pool_back()
            raise
        seconds = time.perf_counter() - t0  # as `workbench track` counts a frame
        source = replace(here.held.source, im_id=nxt)
        same = [m.obj_id for m in done.problem.models] == [m.obj_id for m in e.problem.models]
        view = build_view(done.frame, done.problem, source.title(self.scene_id, nxt), self.dataset,
                          here.held.view.meshes if same else None)
        self.leave()
        here.handed = (est, est.iteration)
        del self.frames[self.at + 1:]
        entry = p.SequenceFrame(nxt, done.status, seconds, done.motion, *run_summary(done.estimator))
        self.frames.append(Processed(entry, HeldRun(source, view, done.frame, done.problem, done.estimator)))
        self.at = len(self.frames) - 1
        return self.frames[self.at].held

    def show(self, im_id: int) -> HeldRun | None:
        """Show the processed frame ``im_id`` again, its run as it was left -> that run, to put on show (None: it is
        on show already, and the server was told the timeline again)."""
        ids = [f.entry.im_id for f in self.frames]
        if self.scene_id is None or im_id not in ids:
            raise InputError("Frame", f"frame {im_id} has not been processed (processed: {ids or 'none'}); Next frame "
                                      "tracks the frame after the one on show")
        i = ids.index(im_id)
        if self.frames[i].held is None:
            raise InputError("Frame", f"frame {im_id}'s run is not in the loaded session (a session keeps the run of "
                                      "the frame on show when it was saved); Next frame goes on from the frame on show")
        if i == self.at:
            self.publish()
            return None
        self.leave()
        self.at = i
        return self.frames[i].held

    def frame_problem(self, im_id: int, T_cam_world: np.ndarray) -> tuple[object, object]:
        """Frame ``im_id`` of the scene and its problem in the sequence's table frame, its camera at
        ``T_cam_world`` (4, 4) (kept where the dataset gives the frame a table pose: the same table's), with the
        frame on show's objects and problem settings."""
        from workbench.io import bop
        from workbench.problem.build import problem_for_frame

        e = self.on_show()
        frame = bop.load_frame(self.dataset, self.scene_id, im_id, self.split, list(e.frame.object_ids))
        if frame.camera.T_cam_world is None:
            frame = replace(frame, camera=frame.camera.with_pose(np.asarray(T_cam_world, dtype=np.float64)))
        models = {m.obj_id: m for m in e.problem.models}
        return frame, problem_for_frame(frame, models, e.problem.config)

    def visit(self, im_id: int, T_cam_world: np.ndarray) -> HeldRun:
        """Show frame ``im_id``, which the timeline has not processed, to label it: a fresh run on it (no
        iteration yet; Step or Run estimates it from scratch), its camera at ``T_cam_world`` (4, 4) in the
        sequence's table frame, joins the timeline in image-id order, status "labelling". It holds no tracked run:
        a Next from the frame before it tracks that frame anew, dropping this one as any frame after it -> the run
        to put on show."""
        from workbench.app.engine.observation import build_view
        from workbench.inference.estimator import Estimator

        e, here = self.on_show(), self.here()
        frame, problem = self.frame_problem(im_id, T_cam_world)
        source = replace(here.held.source, im_id=im_id)
        view = build_view(frame, problem, source.title(self.scene_id, im_id), self.dataset, here.held.view.meshes)
        # The pool is given this frame's problem when the run is put on show (Engine.put_on_show).
        held = HeldRun(source, view, frame, problem, Estimator(problem, e.config, self.evaluators.evaluator()))
        self.leave()
        entry = p.SequenceFrame(im_id, "labelling", 0.0, "", *run_summary(held.estimator))
        at = sum(f.entry.im_id < im_id for f in self.frames)
        self.frames.insert(at, Processed(entry, held))
        self.at = at
        return held

    # -- the frame on show

    def here(self) -> Processed:
        if self.scene_id is None:
            raise InputError("Next frame", "the loaded frame's scene has no other frames: load a frame of a scene "
                                           "with several (a sequence) in the Data tab")
        return self.frames[self.at]

    def next_id(self) -> int | None:
        """The scene's image id after the one on show, or None on its last."""
        i = self.frame_ids.index(self.frames[self.at].entry.im_id) + 1
        return self.frame_ids[i] if i < len(self.frame_ids) else None

    def leave(self) -> None:
        """The frame on show is left: its run, as it is now (the user may have stepped or reset it), is kept, and
        its entry says where it got to."""
        here = self.frames[self.at]
        here.held = replace(here.held, estimator=self.on_show().estimator)
        self.update_entry(here)

    def update_entry(self, here: Processed) -> None:
        """The entry of the frame on show, from its run now: its answer and, for the first frame, its seconds (its
        iterations')."""
        est = self.on_show().estimator
        seconds, status = here.entry.seconds, here.entry.status
        if status in (NOT_RUN, ESTIMATED):
            seconds = float(sum(r.timings.get("total", 0.0) for r in est.history))
            status = ESTIMATED if est.history else NOT_RUN
        positions, confidences = run_summary(est)
        here.entry = replace(here.entry, status=status, seconds=seconds, positions=positions,
                             confidences=confidences)

    def stepped(self) -> None:
        """The run on show made an iteration: a first frame not run yet says it is estimated (once; its numbers
        follow when it finishes or is left)."""
        if self.scene_id is not None and self.frames[self.at].entry.status == NOT_RUN:
            self.update_entry(self.frames[self.at])
            self.publish()

    def finished(self) -> None:
        """The run on show finished (settled): its entry follows, for the timeline and the plots."""
        if self.scene_id is not None:
            self.update_entry(self.frames[self.at])
            self.publish()

    def pool_back(self) -> None:
        """After a failed Next: the evaluator back on the frame on show (a fresh pool where the old one broke)."""
        e, evaluators = self.on_show(), self.evaluators
        if evaluators.problem is e.problem:
            return
        try:
            e.estimator.evaluator = evaluators.retarget(e.problem)
        except Exception:  # noqa: BLE001 - a worker died with the failed Next: start the pool again
            evaluators.use(e.problem)
            e.estimator.evaluator = evaluators.evaluator()

    # -- telling the server, and sessions

    def publish(self, reports: list[dict] | None = None) -> None:
        """The timeline as it stands; ``reports``: the history of the run on show, where the frame on show changed
        (with its settings, where they are not the panel's)."""
        e = self.on_show()
        if self.scene_id is None:
            self.results.put(p.SequenceState(None))
            return
        est = e.estimator
        own = est is not None and replace(est.config, seed=e.config.seed) != e.config
        self.results.put(p.SequenceState(
            self.scene_id, self.frame_ids, [replace(f.entry, held=f.held is not None) for f in self.frames],
            self.frames[self.at].entry.im_id, self.next_id(), reports, est.config if own else None))

    def record(self) -> SequenceRecord | None:
        """The position a session saves (None outside a sequence)."""
        if self.scene_id is None:
            return None
        self.update_entry(self.frames[self.at])
        return SequenceRecord([f.entry for f in self.frames], self.frames[self.at].entry.im_id, self.on_show().config)
