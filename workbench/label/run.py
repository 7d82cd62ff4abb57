"""``workbench label``: a sequence pre-labelled in one go, for a person to review in ``serve``.

1. track: every frame estimated as ``workbench track`` does (the first from scratch, each next one from the one
   before), each frame's problem and answer kept in the sequence's world frame (the tracked table frame);
2. fit to all frames: each still object's pose chosen among the frames' answers and fitted on a spread of the
   frames at once (``multiview``); physics says how far it would move each label to rest (and, asked to, snaps
   them: ``LabelConfig.snap``);
3. carry and check: the labels carried to every frame by its camera pose and checked against its depth
   (``check``); an object flagged in a frame where that frame's own answer passes has moved there: its label takes
   that pose from that frame on;
4. the labels written (``sequence.write_sequence``) with their scene_gt_info entries and provenance.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.evaluation import LocalEvaluator
from workbench.inference.config import EstimatorConfig
from workbench.io import bop
from workbench.label.check import CheckConfig, ObjectCheck, check_objects, render_alone, worst
from workbench.label.config import LabelConfig
from workbench.label.frame import snap_to_plausible
from workbench.label.multiview import MultiView, choose, fit, spread
from workbench.label.sequence import ObjectLabel, SequenceLabels, gt_info_entry
from workbench.problem.problem import Problem, ProblemConfig
from workbench.render.depth import DepthRenderer
from workbench.track.config import TrackConfig
from workbench.track.sequence import Tracker


@dataclass
class LabelRun:
    """What ``label_sequence`` made: the ``labels``, each frame's ``checks`` and scene_gt_info entries
    (``infos``), each frame's own tracked answer (``tracked``: image id -> (K, 4, 4) world), the wall
    ``seconds`` of each stage (track, fit, check) and how far physics moves each fitted label to rest
    (``rest_shift`` (K,) metres)."""

    labels: SequenceLabels
    checks: dict[int, list[ObjectCheck]]
    infos: dict[int, list[dict | None]]
    tracked: dict[int, np.ndarray]
    seconds: dict[str, float]
    rest_shift: np.ndarray | None = None

    @property
    def flagged(self) -> list[int]:
        return [i for i in self.labels.frames if any(c.flagged for c in self.checks.get(i, []))]


def track_all(tracker: Tracker, frames: list[int], keep: set[int], echo: bool = True
              ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray], dict[int, Problem]]:
    """Step ``tracker`` over ``frames`` -> (each frame's camera pose T_cam_world (4, 4) in the tracked world frame,
    its answer (K, 4, 4) world, the problems of the frames in ``keep``). A frame without depth has neither."""
    cams, answers, problems = {}, {}, {}
    for im_id in frames:
        result = tracker.step(im_id)
        if echo:
            print(result.line, file=sys.stderr)
        frame, problem = tracker.previous if tracker.previous is not None else (None, None)
        if frame is None or frame.im_id != im_id:  # lost as a whole: no depth, nothing to label against
            continue
        cams[im_id] = problem.camera.T_cam_world.copy()
        answers[im_id] = tracker.carried.settled.copy()
        if im_id in keep:
            problems[im_id] = problem
    return cams, answers, problems


def fitted_labels(problems: dict[int, Problem], answers: dict[int, np.ndarray], config: LabelConfig
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """The still labels (K, 4, 4) world: the first frame's answer, each object's pose chosen among every frame's
    answer and fitted on ``problems``' frames at once within ``config.settle_shift`` and ``settle_turn`` of it; with
    ``config.snap``, then put at rest by physics and fitted again within that region of the rest, as the estimator
    settles its answer.
    -> (the labels, how far physics moves each label to put the scene at rest (K,) metres: its plausibility; None
    without frames to fit to, where nothing was simulated).

    Physics is off by default: on the real sequences it lifts every label 7-16 mm (the table's plane, fitted to the
    depth, lies above the real support), and fitting again within the settling region brings most of it back but
    not all, so the snapped labels were further from the truth than the fitted ones (docs/journal/2026-12.md,
    "Sequence labels")."""
    first = min(answers)
    T = answers[first]
    if not problems:
        return T, None
    used = sorted(problems)
    problem = problems[used[0]]
    view = MultiView([problems[i] for i in used], np.ones((len(used), len(problem.models)), dtype=bool))
    evaluator = LocalEvaluator(problem)
    try:
        candidates = [[answers[i][k] for i in sorted(answers)] for k in range(len(problem.models))]
        T = choose(view, T, candidates, [m.symmetries for m in problem.models])
        # Within the settling region of the chosen pose: the fit refines, it does not relocate (an object taken out
        # on some frames would otherwise be pushed where those frames see nothing of it).
        T = fit(view, T, max_shift_m=config.settle_shift, max_turn_deg=config.settle_turn)
        rested, moved, _ = snap_to_plausible(problem, T, evaluator)
        if config.snap:
            T = fit(view, rested, max_shift_m=config.settle_shift, max_turn_deg=config.settle_turn)
    finally:
        view.close()
        evaluator.close()
    return T, moved


class FrameChecker:
    """Renders each label alone at a frame's full resolution (one renderer for the sequence: its camera at the
    origin, the labels given in the camera frame) and checks it against the frame's depth."""

    def __init__(self, dataset: Path, scene_id: int, split: str | None, object_ids: list[int], models: dict,
                 config: CheckConfig):
        self.dataset, self.scene_id, self.split, self.object_ids = dataset, scene_id, split, object_ids
        self.config = config
        self.renderer: DepthRenderer | None = None
        self.models = [models[i] for i in object_ids]
        self._depth: tuple[int, np.ndarray] | None = None  # the last frame read: checked again after a move

    def depth(self, im_id: int) -> np.ndarray:
        """Frame ``im_id``'s observed depth (H, W) metres, read once however often the frame is checked in a row."""
        if self._depth is None or self._depth[0] != im_id:
            frame = bop.load_frame(self.dataset, self.scene_id, im_id, self.split, self.object_ids)
            if self.renderer is None:
                self.renderer = DepthRenderer(frame.camera.with_pose(np.eye(4)), [m.mesh for m in self.models])
            self._depth = im_id, frame.depth
        return self._depth[1]

    def check(self, im_id: int, T_cam_obj: list[np.ndarray | None]) -> tuple[list[ObjectCheck], list[dict | None]]:
        """Frame ``im_id``'s labels (per object T_cam_obj (4, 4) or None) -> (their checks, scene_gt_info
        entries)."""
        depth = self.depth(im_id)
        present = np.array([T is not None for T in T_cam_obj])
        poses = np.array([np.eye(4) if T is None else T for T in T_cam_obj])
        alone = render_alone(self.renderer, poses, present)
        checks = check_objects(self.object_ids, alone, depth, self.config)
        infos = [gt_info_entry(a, depth) if p else None for a, p in zip(alone, present)]
        return checks, infos

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()


def carry_and_check(labels: SequenceLabels, answers: dict[int, np.ndarray], checker: FrameChecker
                    ) -> tuple[dict[int, list[ObjectCheck]], dict[int, list[dict | None]]]:
    """Every frame's labels checked in order; an object flagged where the frame's own answer (``answers``, world)
    passes the check has moved: its label takes that pose from that frame on (``SequenceLabels.moved_to``) ->
    (each frame's checks, its scene_gt_info entries)."""
    checks, infos = {}, {}
    for im_id in labels.frames:
        T_cw = labels.T_cam_world[im_id]
        rows, info = checker.check(im_id, labels.camera_poses(im_id))
        flagged = [k for k, c in enumerate(rows) if c.flagged]
        if flagged and im_id in answers:
            own = [T_cw @ answers[im_id][k] if labels.objects[k].pose_at(im_id) is not None else None
                   for k in range(len(labels.objects))]
            own_rows, _ = checker.check(im_id, own)
            moved = [k for k in flagged if own_rows[k].checked and not own_rows[k].flagged]
            for k in moved:
                labels.moved_to(k, im_id, answers[im_id][k])
            if moved:
                rows, info = checker.check(im_id, labels.camera_poses(im_id))
        checks[im_id], infos[im_id] = rows, info
    return checks, infos


def label_sequence(dataset: Path, scene_id: int, frames: list[int], config: EstimatorConfig, track: TrackConfig,
                   label: LabelConfig, problem_config: ProblemConfig = ProblemConfig(), workers: int = 2,
                   split: str | None = None, object_ids: list[int] | None = None, early_stop: bool = True
                   ) -> LabelRun:
    """Pre-label scene ``scene_id``'s ``frames`` (image ids in order; see the module) -> the run. Every frame is
    labelled with the first frame's objects (``object_ids``, default its scene_gt.json's)."""
    label.validate()
    object_ids = object_ids or bop.load_frame(dataset, scene_id, frames[0], split).object_ids
    for obj_id, last in label.ends.items():
        if obj_id not in object_ids:
            raise InputError("--end", f"object {obj_id} is not in scene {scene_id} (objects {object_ids})")
    seconds = {}
    t0 = time.perf_counter()
    tracker = Tracker(dataset, scene_id, frames, config, track, problem_config, workers, split, object_ids,
                      early_stop)
    try:
        keep = set(spread(frames, label.fit_frames)) if label.fit_frames else set()
        cams, answers, problems = track_all(tracker, frames, keep)
    finally:
        tracker.close()
    if not answers:
        raise InputError(f"scene {scene_id}", "no frame of the sequence has depth to label against")
    models = tracker.models
    seconds["track"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    T, rest_shift = fitted_labels(problems, answers, label)
    seconds["fit"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    objects = [ObjectLabel(obj_id, T[k].copy(), last=label.ends.get(obj_id)) for k, obj_id in enumerate(object_ids)]
    labels = SequenceLabels(scene_id, cams, objects)
    checker = FrameChecker(dataset, scene_id, split, object_ids, models, label.check)
    try:
        checks, infos = carry_and_check(labels, answers, checker)
    finally:
        checker.close()
    seconds["check"] = time.perf_counter() - t0
    return LabelRun(labels, checks, infos, answers, seconds, rest_shift)


def flag_table(run: LabelRun) -> list[str]:
    """The flagged frames as lines of a table: frame, worst object, its agreement, why."""
    lines = []
    for im_id in run.flagged:
        for c in run.checks[im_id]:
            if c.flagged:
                lines.append(f"  frame {im_id:>6}  object {c.obj_id:>3}  agrees on {c.agree:4.0%} of "
                             f"{c.pixels:>6} px: {c.reason}")
    return lines


def gone_from(run: LabelRun) -> dict[int, int]:
    """Objects whose label is flagged as seen through on every frame from some frame to the last: object id ->
    that frame (taken out there? ``--end OBJ:FRAME`` ends its label on the frame before)."""
    frames = run.labels.frames
    out = {}
    for k, obj_id in enumerate(run.labels.obj_ids):
        start = None
        for im_id in reversed(frames):
            c = run.checks[im_id][k]
            if not (c.flagged and c.through >= c.front):
                break
            start = im_id
        if start is not None and start != frames[0]:
            out[obj_id] = start
    return out


def summary(run: LabelRun) -> str:
    """One line: frames labelled, flagged, the worst agreement, the stages' seconds."""
    worsts = [w for i in run.labels.frames if (w := worst(run.checks[i])) is not None]
    s = run.seconds
    rest = "" if run.rest_shift is None else f"; physics would move a label up to {1000 * max(run.rest_shift):.0f} mm"
    worst_text = f"worst agreement {min(worsts):.0%}" if worsts else "no object could be checked"
    return (f"labelled {len(run.labels.frames)} frame(s) of scene {run.labels.scene_id}: {len(run.flagged)} "
            f"flagged; {worst_text}{rest} (track {s['track']:.1f} s, fit {s['fit']:.1f} s, check {s['check']:.1f} s)")

