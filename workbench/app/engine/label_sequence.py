"""A whole sequence's labels on the engine's side (issue 68): one label per object in the sequence's table frame,
carried to every frame by its camera pose and checked against that frame's depth (``workbench.label``).

The labels start from the Label tab's labels on the frame on show, or from the labels saved before
(scene_gt_labels.json, read back frame by frame). Then:
- *Propagate*: the label edited on the frame on show becomes that object's pose on every frame, or from that frame
  on (``SequenceLabels.moved_to``);
- *End label*: an object seen through from some frame on (``run.gone_from``) ends on the frame before;
- *Fit to all frames*: the still labels fitted to a spread of frames at once, as ``workbench label`` fits them
  (``multiview``; physics only with ``LabelConfig.snap``, off as there);
- *Save*: ``write_sequence`` to scene_gt_labels.json and its info and provenance files (the scene's own files only
  when the user ticks overwrite; backups kept).
After each change every frame is checked again (``FrameChecker``: full resolution) and the server is sent the
state (``protocol.SequenceLabelState``). The frames' own answers are not used to move labels, unlike
``run.carry_and_check``: here the person decides, and a label they moved must stay where they put it.

The frames share the sequence's table frame (the frames the timeline processed, ``engine.sequence``). A frame the
timeline has not processed gets its camera pose from the dataset (a table pose per frame, or the camera's world
poses in scene_camera_world.json), else by registering its depth to its neighbour's, as ``workbench track`` does.
Like the other helpers it changes none of the engine's fields: showing a frame returns the run to put on show.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from workbench.app import protocol as p
from workbench.app.engine.labels import FrameLabels, movement_table, turned
from workbench.app.engine.on_show import RunOnShow
from workbench.app.engine.sequence import EngineSequence, HeldRun, told
from workbench.app.engine.sequence_cameras import sequence_cameras
from workbench.errors import InputError

TOPIC = "sequence labels"
PROGRESS_EVERY_S = 1.0  # how often a long check tells the server how far it got


def carried_labels(scene_id: int, cams: dict[int, np.ndarray], obj_ids: list[int], current: list[np.ndarray],
                   shown: int, P: np.ndarray):
    """The labels ``current`` (per object (4, 4)) of frame ``shown``, whose problem's camera is ``P`` (4, 4), as
    the sequence's still labels on the frames of ``cams`` (image id -> T_cam_world (4, 4)): a person checked that
    frame."""
    from workbench.geometry import invert_pose
    from workbench.label.sequence import ObjectLabel, SequenceLabels

    to_sequence = invert_pose(cams.get(shown, P)) @ P  # the identity, unless the frame's support fit moved it
    labels = SequenceLabels(scene_id, cams, [ObjectLabel(i, to_sequence @ T) for i, T in zip(obj_ids, current)])
    labels.checked = {shown} & set(cams)
    return labels


def check_frames(labels, checker, tell: Callable[[object], None]) -> tuple[dict[int, list], dict[int, list]]:
    """Every frame of ``labels`` (``SequenceLabels``) checked by ``checker`` (``run.FrameChecker``) -> (per image id
    its ``ObjectCheck``s, its scene_gt_info entries). A long check ``tell``s how far it got, every second. The
    frames' own answers do not move labels here (``run.carry_and_check`` would): the person decides."""
    checks, infos = {}, {}
    told = time.monotonic()
    for n, im in enumerate(labels.frames):
        if time.monotonic() - told > PROGRESS_EVERY_S:
            tell(p.SequenceLabelProgress(f"Checking frame {im} ({n + 1} of {len(labels.frames)}) …"))
            told = time.monotonic()
        checks[im], infos[im] = checker.check(im, labels.camera_poses(im))
    return checks, infos


def fit_still(problems: list, present: np.ndarray, T: np.ndarray, snap: Callable[[np.ndarray], np.ndarray],
              config, tell: Callable[[object], None]) -> np.ndarray:
    """``run.fitted_labels``' steps from given labels: the scene ``T`` (K, 4, 4) fitted to ``problems`` (one per
    frame, the sequence's table frame; ``present`` (F, K) the labels each draws) at once, with no bound (unlike
    ``workbench label``'s, which refines the frames' own answers: a label moved by hand may be centimetres off);
    with ``config.snap``, then ``snap``ped by physics and fitted again within ``config.settle_shift`` m and
    ``settle_turn`` degrees of the rest -> (K, 4, 4)."""
    from workbench.label.multiview import MultiView, fit

    view = MultiView(problems, present)
    try:
        tell(p.SequenceLabelProgress(f"Fitting the labels to {len(problems)} frames at once …"))
        T = fit(view, T)
        if config.snap:
            tell(p.SequenceLabelProgress("Snapping the fitted labels with physics, fitting again …"))
            T = fit(view, snap(T), max_shift_m=config.settle_shift, max_turn_deg=config.settle_turn)
        return T
    finally:
        view.close()


def state_message(labels, checks: dict[int, list], infos: dict[int, list], note: str) -> p.SequenceLabelState:
    """What the server is sent of ``labels`` (``SequenceLabels``) and each frame's ``checks``: per frame its worst
    agreement and checks, the objects seen through to the end (``run.gone_from``), and ``note``."""
    from workbench.label.check import worst
    from workbench.label.run import LabelRun, gone_from

    frames = [p.LabelledFrame(i, worst(checks[i]), any(c.flagged for c in checks[i]),
                              [{**c.to_dict(), "reason": c.reason} for c in checks[i]], i in labels.checked)
              for i in labels.frames]
    gone = gone_from(LabelRun(labels, checks, infos, {}, {}))
    ids = labels.obj_ids
    return p.SequenceLabelState(labels.scene_id, frames, [(ids.index(o), o, f) for o, f in sorted(gone.items())],
                                note)


def save_labels(labels, checks: dict[int, list], infos: dict[int, list], dataset: Path, split: str | None,
                overwrite_original: bool) -> p.Saved:
    """``write_sequence`` to the scene's default files (scene_gt_labels.json and the two beside it), or with
    ``overwrite_original`` its own scene_gt.json and scene_gt_info.json, backed up first -> what to tell."""
    from workbench.label.frame import kept_note
    from workbench.label.sequence import label_files, write_sequence

    files = label_files(dataset, labels.scene_id, split, overwrite_original=overwrite_original)
    started = time.time()
    written = write_sequence(files, labels, infos, checks)
    note = f"{len(labels.frames)} frames; also `{written[1].name}`, `{written[2].name}`"
    if overwrite_original:
        note += f"; {kept_note(files.labels, started)}"
    return p.Saved("sequence labels", str(files.labels), note)


class SequenceLabelling:
    """The sequence's labels (``labels``: ``SequenceLabels`` or None), their checks and scene_gt_info entries per
    frame, and the commands that change them. Given only what it uses of the engine: ``results``, the frame's
    labels (``frame_labels``: the Label tab's, and the renderer of the frame on show), the ``sequence`` (its
    dataset, frames and processed runs) and ``on_show``."""

    def __init__(self, results, frame_labels: FrameLabels, sequence: EngineSequence,
                 on_show: Callable[[], RunOnShow]):
        from workbench.label.config import LabelConfig

        self.results, self.frame_labels, self.sequence, self.on_show = results, frame_labels, sequence, on_show
        self.config = LabelConfig()
        self.labels = None  # label.sequence.SequenceLabels
        self.checks: dict[int, list] = {}
        self.infos: dict[int, list] = {}
        self.checker = None  # label.run.FrameChecker, for ``checker_key``'s frames
        self.checker_key: tuple | None = None
        self.unsaved = False  # changed since the labels were last written or saved in a session
        self.warned = False  # and a load was refused once for it (``refuse_to_drop``)

    # -- guarding

    def guarded(self, action: Callable[[], object]) -> object:
        """Do ``action``: bad input is told beside the sequence labels' buttons and changes nothing (None)."""
        return told(self.results, action, TOPIC, "Sequence labels: not done", "Sequence labels failed")

    def forget(self) -> None:
        """Another sequence (or none) was loaded: its labels start again."""
        self.labels, self.checks, self.infos = None, {}, {}
        self.unsaved = self.warned = False
        self.close()
        self.results.put(p.SequenceLabelState(None))

    def restore(self, labels) -> None:
        """A session's sequence labels (``label.sequence.SequenceLabels``; None: it kept none) on hand again, every
        frame checked anew (a check that fails is told; the labels stay)."""
        self.forget()
        if labels is not None:
            self.labels = labels
            self.guarded(lambda: self.recheck("Restored from the session; every frame checked again"))
            self.unsaved = False

    def refuse_to_drop(self) -> None:
        """Before a frame is loaded from the Data tab (which starts the labels anew): InputError, once, while the
        labels have changes that neither a save nor a session holds; a second try drops them."""
        if self.labels is not None and self.unsaved and not self.warned:
            self.warned = True
            raise InputError("sequence labels", f"the sequence labels of scene {self.labels.scene_id} are not saved, "
                                                "and loading another frame starts them anew: save them (Label tab, "
                                                "Save sequence labels) or a session first, or press Load again to "
                                                "drop them")

    def close(self) -> None:
        if self.checker is not None:
            self.checker.close()
        self.checker, self.checker_key = None, None

    # -- where things are

    def where(self) -> tuple[Path, int, str | None]:
        """The sequence's dataset, scene and split; InputError outside a sequence."""
        seq = self.sequence
        if seq.scene_id is None:
            raise InputError("sequence labels", "the loaded frame's scene has no other frames: load a frame of a "
                                                "sequence in the Data tab")
        return seq.dataset, seq.scene_id, seq.split

    def started(self):
        """The labels; InputError before they are started."""
        if self.labels is None:
            raise InputError("sequence labels", "start them first: Check every frame, from the current labels "
                                                "or the saved ones")
        return self.labels

    def on_show_im(self) -> int:
        return int(self.on_show().frame.im_id)

    def shown_camera(self) -> tuple[np.ndarray, np.ndarray]:
        """The frame on show's camera pose in the sequence's frame and in its own problem's -> (C, P), (4, 4)
        each: its labels map to the sequence's frame as ``inv(C) @ P @ T`` (the same frame, unless the support fit
        of a frame shown for labelling moved its table)."""
        problem = self.on_show().problem
        P = np.asarray(problem.camera.T_cam_world, dtype=np.float64)
        C = self.labels.T_cam_world.get(self.on_show_im(), P) if self.labels is not None else P
        return C, P

    def to_sequence(self, T: np.ndarray) -> np.ndarray:
        from workbench.geometry import invert_pose

        C, P = self.shown_camera()
        return invert_pose(C) @ P @ np.asarray(T, dtype=np.float64)

    def to_shown(self, T: np.ndarray) -> np.ndarray:
        from workbench.geometry import invert_pose

        C, P = self.shown_camera()
        return invert_pose(P) @ C @ np.asarray(T, dtype=np.float64)

    def processed_cameras(self) -> dict[int, np.ndarray]:
        """The camera poses of the frames the timeline processed (their runs' problems), the frame on show's
        included."""
        out = {f.entry.im_id: f.held.problem.camera.T_cam_world for f in self.sequence.frames if f.held is not None}
        out[self.on_show_im()] = self.on_show().problem.camera.T_cam_world
        return out

    # -- commands

    def check(self, cmd: p.CheckSequenceLabels) -> None:
        """Start the labels (``cmd.start``) on ``cmd.frames`` and check every frame. Everything is read before the
        labels on hand are replaced: bad input leaves them as they were."""
        from workbench.label import frame as labelling
        from workbench.label.sequence import from_frame_poses, label_files
        from workbench.track.frames import sequence_frames

        dataset, scene_id, split = self.where()
        run = self.on_show()
        if cmd.start not in ("current", "saved"):
            raise InputError("start", f"must be 'current' or 'saved', got {cmd.start!r}")
        frames = sequence_frames(dataset, scene_id, split, cmd.frames.strip() or None)
        obj_ids = [int(i) for i in run.frame.object_ids]
        current = list(self.frame_labels.labels)
        if cmd.start == "current":
            missing = [n for n, T in zip(self.frame_labels.names(), current) if T is None]
            if missing:
                raise InputError("labels", f"label every object on this frame first ({', '.join(missing)} not "
                                           "labelled): Use best estimate as label, then correct it")
        else:
            path = label_files(dataset, scene_id, split).labels
            if not path.is_file():
                raise InputError(path, "not found: no sequence labels were saved for this scene yet")
        self.results.put(p.SequenceLabelProgress(f"Finding the camera poses of {len(frames)} frames …"))
        t = run.problem.table
        cams = sequence_cameras(dataset, scene_id, split, frames, self.processed_cameras(),
                                (t.region_min, t.region_max))
        if cmd.start == "current":
            shown = self.on_show_im()
            labels = carried_labels(scene_id, cams, obj_ids, current, shown, run.problem.camera.T_cam_world)
            note = f"Started from the labels of frame {shown}, carried to {len(frames)} frames"
        else:
            poses = {i: labelling.load_labels(dataset, scene_id, i, cams[i], obj_ids, path=path, split=split)
                     for i in frames}
            labels = from_frame_poses(scene_id, cams, obj_ids, poses)
            note = f"Read the labels saved in `{path}` for {len(frames)} frames"
        self.labels = labels
        self.recheck(note)
        self.show_on_frame()

    def propagate(self, cmd: p.PropagateLabel) -> None:
        labels = self.started()
        im = self.on_show_im()
        k = self.object_index(cmd.index)
        if im not in labels.T_cam_world:
            raise InputError("Propagate", f"frame {im} is not one of the labelled frames ({labels.frames[0]}.."
                                          f"{labels.frames[-1]}): show one with the timeline")
        T = self.frame_labels.labels[k] if k < len(self.frame_labels.labels) else None
        if T is None:
            raise InputError("Propagate", f"object {self.names()[k]} has no label on frame {im}")
        T = self.to_sequence(T)
        o = labels.objects[k]
        if cmd.from_here:
            labels.moved_to(k, im, T)
            how = f"from frame {im} on"
        else:
            from workbench.geometry import check_rigid

            o.T_world_obj, o.moves = check_rigid(T, f"label of object {o.obj_id}"), {}
            how = "on every frame"
        labels.checked.add(im)
        self.recheck(f"**Propagated** {self.names()[k]}'s label of frame {im} {how}")

    def end(self, cmd: p.EndSequenceLabel) -> None:
        labels = self.started()
        k = self.object_index(cmd.index)
        if cmd.last not in labels.T_cam_world:
            raise InputError("End label", f"frame {cmd.last} is not one of the labelled frames")
        labels.ends_at(k, cmd.last)
        self.recheck(f"**Ended** {self.names()[k]}'s label on frame {cmd.last} (taken out after it)")
        self.show_on_frame()

    def fit(self) -> None:
        """The still labels (objects that never move) fitted to ``config.fit_frames`` frames spread over the
        sequence at once; with ``config.snap``, snapped by physics on the frame on show's table and fitted again
        within the settling's reach of the rest (``fit_still``: ``run.fitted_labels``' steps, from the labels
        instead of the frames' answers)."""
        from workbench.label import frame as labelling
        from workbench.label.multiview import spread

        labels = self.started()
        still = [k for k, o in enumerate(labels.objects) if not o.moves]
        if not still:
            raise InputError("Fit to all frames", "every object's label moves during the sequence: fit them on "
                                                  "their frames one at a time (the Label tab's Fit to depth)")
        used = spread(labels.frames, self.config.fit_frames)
        self.results.put(p.SequenceLabelProgress(f"Fitting: building the problems of {len(used)} frames …"))
        problems = [self.problem_for(i) for i in used]
        present = np.array([labels.world_poses(i)[1] for i in used])
        before = np.array([o.T_world_obj for o in labels.objects])
        run = self.on_show()

        def snap(T: np.ndarray) -> np.ndarray:
            # Physics on the frame on show's table: the sequence's table frame, the same table in every frame.
            shown = np.array([self.to_shown(U) for U in T])
            snapped, _, _ = labelling.snap_to_plausible(run.problem, shown, self.frame_labels.evaluators.local())
            return np.array([self.to_sequence(U) for U in snapped])

        T = fit_still(problems, present, before, snap, self.config, self.results.put)
        for k in still:
            labels.objects[k].T_world_obj = T[k].copy()
        moved = np.linalg.norm(T[:, :3, 3] - before[:, :3, 3], axis=-1)
        table = movement_table(self.names(), still, moved, turned(before, T))
        snapped = ", snapped and fitted again" if self.config.snap else ""
        self.recheck(f"**Fitted** the still labels to frames {', '.join(map(str, used))} at once{snapped}"
                     f"\n\n{table}")
        self.show_on_frame()

    def save(self, cmd: p.SaveSequenceLabels):
        """Write the labels -> the frame on show with its ground truth read again where scene_gt.json was
        overwritten (for the engine to put on show), else None."""
        from workbench.app.engine.label_files import reread_truth

        labels = self.started()
        dataset, _, split = self.where()
        self.results.put(save_labels(labels, self.checks, self.infos, dataset, split, cmd.overwrite_original))
        self.unsaved = False
        if cmd.overwrite_original and self.frame_labels.frame_ref is not None:
            return reread_truth(self.frame_labels, self.on_show(), dataset, split)
        return None

    def held_for(self, im_id: int) -> HeldRun | None:
        """The run to show frame ``im_id`` with: its processed run, or a fresh run on it (``sequence.visit``);
        None where it is on show already."""
        labels = self.started()
        if im_id not in labels.T_cam_world:
            raise InputError("Frame", f"frame {im_id} is not one of the labelled frames ({labels.frames[0]}.."
                                      f"{labels.frames[-1]})")
        if im_id == self.on_show_im():
            self.show_on_frame()
            return None
        if any(f.entry.im_id == im_id and f.held is not None for f in self.sequence.frames):
            return self.sequence.show(im_id)
        return self.sequence.visit(im_id, labels.T_cam_world[im_id])

    # -- after a change

    def problem_for(self, im_id: int):
        """Frame ``im_id``'s problem in the sequence's table frame (the processed run's where there is one)."""
        for f in self.sequence.frames:
            if f.entry.im_id == im_id and f.held is not None:
                return f.held.problem
        return self.sequence.frame_problem(im_id, self.labels.T_cam_world[im_id])[1]

    def recheck(self, note: str) -> None:
        """Every frame's labels checked against its depth; the state sent with ``note``."""
        from workbench.label.run import FrameChecker

        labels = self.started()
        dataset, scene_id, split = self.where()
        key = (str(dataset), scene_id, split, tuple(labels.obj_ids))
        if self.checker_key != key:
            self.close()
            models = {m.obj_id: m for m in self.on_show().problem.models}
            self.checker = FrameChecker(dataset, scene_id, split, labels.obj_ids, models, self.config.check)
            self.checker_key = key
        self.checks, self.infos = check_frames(labels, self.checker, self.results.put)
        self.unsaved, self.warned = True, False  # every change of the labels is checked again here
        self.publish(note)

    def show_on_frame(self) -> None:
        """The Label tab shows the sequence's labels of the frame on show (where it is one of theirs)."""
        labels, im = self.labels, self.on_show_im()
        if labels is None or im not in labels.T_cam_world:
            return
        poses, present = labels.world_poses(im)
        fl = self.frame_labels
        fl.labels = [self.to_shown(T) if here else None for T, here in zip(poses, present)]
        fl.reference = None
        fl.dirty = True
        self.results.put(p.Labels(list(fl.labels), "sequence", f"The sequence's labels on frame {im}"))

    def publish(self, note: str = "") -> None:
        self.results.put(p.SequenceLabelState(None) if self.labels is None
                         else state_message(self.labels, self.checks, self.infos, note))

    # -- small parts

    def names(self) -> list[str]:
        return self.frame_labels.names()

    def object_index(self, index: int) -> int:
        n = len(self.labels.objects)
        if not 0 <= index < n:
            raise InputError("object", f"no object {index}: the sequence has {n}")
        return index
