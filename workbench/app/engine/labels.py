"""The labels of the loaded frame, on the engine's side: where they come from (the dataset's label file, a session,
the user's edits), what is computed from them (snap, fit, the labelled scene's heatmap, the estimate's errors, the
known scene's log-likelihood for the Plots tab) and saving them.

This runs in the engine process because it needs the estimator and a renderer: the server only shows the labels.
Label edits arrive as ``SetLabels`` on every gizmo move; only the latest is kept, and its heatmap and errors are
computed once the command queue is drained (``work``), so a fast drag costs one render per pass.
"""

from __future__ import annotations

import logging
import time
import traceback
from pathlib import Path
from typing import Callable

import numpy as np

from workbench.app import protocol as p
from workbench.app.engine.evaluators import CRASH_ERRORS
from workbench.app.engine.on_show import RunOnShow
from workbench.errors import InputError

log = logging.getLogger(__name__)


def turned(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """How far each object (K,) turned from scene ``a`` to scene ``b`` (K, 4, 4), in degrees."""
    from workbench.geometry import rotation_angle

    return np.degrees(rotation_angle(np.swapaxes(a[:, :3, :3], -1, -2) @ b[:, :3, :3]))


def truth_points(problem) -> list:
    """Per object the ADD-S points of ``workbench score`` (score.scoring: 500 surface samples, seed 0)."""
    from workbench.score.metrics import model_points

    return [model_points(m.mesh, 500) for m in problem.models]


def truth_scene(frame, problem) -> np.ndarray | None:
    """``frame``'s ground truth (K, 4, 4) in ``problem``'s table frame when it has a pose for every object, else
    None (also with no frame or problem loaded)."""
    if frame is None or problem is None or frame.gt_T_cam_obj is None:
        return None
    from workbench.geometry import invert_pose

    gt = invert_pose(problem.camera.T_cam_world)[None] @ frame.gt_T_cam_obj
    return gt if len(gt) == problem.n_objects and np.all(np.isfinite(gt)) else None


def movement_table(names: list[str], which: list[int], moved: np.ndarray, turns: np.ndarray) -> str:
    """Markdown table of how far each labelled object (``which``) moved (m -> cm) and turned (deg)."""
    rows = "\n".join(f"| {names[k]} | {moved[k] * 100:.2f} | {turns[k]:.1f} |" for k in which)
    return f"| object | moved (cm) | turned (°) |\n|---|---:|---:|\n{rows}"


class FrameLabels:
    """Per object of the frame on show a (4, 4) table-frame pose or None, and the frame's place in its dataset
    (``frame_ref``; None: label files and sessions unavailable, ``frame_ref_problem`` says why). Given only what it
    uses of the engine: ``results`` (what the server is told), the ``evaluators`` (renders) and ``on_show`` (-> the
    run on show, read-only)."""

    def __init__(self, results, evaluators, on_show: Callable[[], RunOnShow]):
        self.results = results
        self.evaluators = evaluators
        self.on_show = on_show
        self.frame_ref = None
        self.frame_ref_problem = "nothing is loaded"
        self.labels: list[np.ndarray | None] = []
        self.heatmap = False
        self.dirty = False  # labels changed: heatmap and errors to recompute once the queue is drained
        # The log-likelihood of the known scene the Plots tab compares the estimate with: (kind, value) or None
        # while not yet computed; dropped whenever the labels, the frame or the likelihood change.
        self.reference: dict[str, float] | None = None
        self.truth_points: list | None = None  # per object the ADD-S points ``workbench score`` uses

    def adopt_frame(self, dataset: Path, labels: list | None = None) -> None:
        """Note where the loaded frame lives in its dataset (sessions and label files need it) and take its labels:
        ``labels`` (a session's), else those saved beside the dataset's ground truth, if any."""
        from workbench.label import frame as labelling
        from workbench.sessions import store as sessions

        run, results = self.on_show(), self.results
        frame, problem = run.frame, run.problem
        try:
            self.frame_ref, self.frame_ref_problem = sessions.frame_ref_for(dataset, frame, problem), ""
        except (InputError, OSError) as err:
            self.frame_ref, self.frame_ref_problem = None, str(err)
        note, reason = "", "session" if labels is not None else "frame"
        if labels is None:
            labels = [None] * problem.n_objects
            if self.frame_ref is not None:
                ref = self.frame_ref
                try:
                    labels = labelling.load_labels(Path(ref.dataset), frame.scene_id, frame.im_id,
                                                   problem.camera.T_cam_world, list(frame.object_ids), split=ref.split)
                except InputError as err:
                    results.put(p.Failure("Labels: not read", err.problem, err.path, topic="labels"))
                n = sum(T is not None for T in labels)
                if n:
                    where = labelling.labels_path(Path(ref.dataset), frame.scene_id, ref.split)
                    note = f"{n} label(s) read from `{where}`"
        self.labels = [None if T is None else np.array(T, dtype=np.float64) for T in labels]
        self.reference = None
        self.truth_points = None
        results.put(p.Labels(list(self.labels), reason, note))
        self.dirty = True

    def set(self, cmd: p.SetLabels) -> None:
        problem = self.on_show().problem
        if problem is None or len(cmd.labels) != problem.n_objects:
            return  # edits of a frame that has since been replaced
        self.labels = [None if T is None else np.array(T, dtype=np.float64) for T in cmd.labels]
        self.reference = None
        self.heatmap = cmd.heatmap
        self.dirty = True

    def labelled(self) -> list[int]:
        """The labelled objects; InputError when there are none."""
        which = [k for k, T in enumerate(self.labels) if T is not None]
        if self.on_show().problem is None or not which:
            raise InputError("labels", "nothing is labelled yet: move an object's gizmo, type its pose, or use the "
                                       "best estimate as label")
        return which

    def scene(self, leave_out: bool) -> tuple[np.ndarray, str]:
        """The labels as a whole scene (K, 4, 4) -> (scene, how unlabelled objects were filled in). Physics and the
        likelihood need every object somewhere: unlabelled ones take the best estimate; before the first
        iteration, with ``leave_out``, they are put behind the camera, out of the rendered view, else InputError."""
        from workbench.geometry import invert_pose

        missing = [k for k, T in enumerate(self.labels) if T is None]
        if not missing:
            return np.stack(self.labels), ""
        run = self.on_show()
        est = run.estimator
        if est is not None and est.particles is not None:
            fill, how = est.estimate, "best estimate"
        elif leave_out:
            behind = invert_pose(run.problem.camera.T_cam_world)
            behind[:3, 3] -= 100.0 * behind[:3, 2]  # 100 m behind the sensor: clipped, never drawn
            fill, how = np.broadcast_to(behind, (len(self.labels), 4, 4)), "left out"
        else:
            raise InputError("labels", "label every object, or take one estimator step so that its best estimate "
                                       "can stand in for the unlabelled ones")
        return np.stack([fill[k] if T is None else T for k, T in enumerate(self.labels)]).astype(np.float64), how

    def adopt(self, scene: np.ndarray, which: list[int], reason: str, note: str) -> None:
        """Labels of the objects ``which`` from ``scene``, sent to the server with ``note`` on how they came."""
        for k in which:
            self.labels[k] = np.array(scene[k], dtype=np.float64)
        self.reference = None
        self.results.put(p.Labels(list(self.labels), reason, note))
        self.dirty = True

    def names(self) -> list[str]:
        from workbench.problem.scene import display_names

        return display_names(self.on_show().problem.models)

    def snap(self) -> None:
        from workbench.label import frame as labelling
        from workbench.physics import STATUS_NAMES

        which = self.labelled()
        scene, filled = self.scene(leave_out=False)
        projected, moved, status = labelling.snap_to_plausible(self.on_show().problem, scene,
                                                               self.evaluators.local())
        stand_in = f" (unlabelled objects: the {filled})" if filled else ""
        note = (f"**Snapped**: physics {STATUS_NAMES.get(status, status)}{stand_in}\n\n"
                + movement_table(self.names(), which, moved, turned(scene, projected)))
        self.adopt(projected, which, "snap", note)

    def fit(self) -> None:
        from workbench.label import frame as labelling

        which = self.labelled()
        scene, filled = self.scene(leave_out=False)
        fitted = labelling.fit_label(self.on_show().problem, scene, self.evaluators.local())
        moved = np.linalg.norm(fitted[:, :3, 3] - scene[:, :3, 3], axis=-1)
        stand_in = f" (unlabelled objects: the {filled}, not changed)" if filled else ""
        note = (f"**Fitted** to the depth, then snapped{stand_in}\n\n"
                + movement_table(self.names(), which, moved, turned(scene, fitted)))
        self.adopt(fitted, which, "fit", note)

    def use_best(self, modes: tuple[int, ...] = (), iteration: int = -1) -> bool:
        """Label every object with the settled estimate, or with the mode ``modes`` names for it (indices into the
        modes of the posterior shown with the snapshot of ``iteration``) -> whether the engine is to publish the
        snapshot again: settling gave the run a posterior the server has not seen (its modes, to show and choose
        from)."""
        from workbench.app.ui.run.modes import scene_with_modes

        run = self.on_show()
        est = run.estimator
        if est is None or est.particles is None:
            raise InputError("labels", "there is no estimate yet: take a step first")
        shown = est.answer_current  # the server has this posterior already
        # Settled (Estimator.settle), as `workbench estimate` writes it: the search's scene fitted to the depth.
        settled = est.settle().copy()
        moved = np.linalg.norm(settled[:, :3, 3] - est.estimate[:, :3, 3], axis=-1)
        note = f"Labels set to the most likely scene of iteration {est.iteration}"
        if moved.any():
            note += f", settled to the depth (objects moved up to {moved.max() * 1e3:.1f} mm)"
        # Modes chosen among those of another estimate would be other poses: only the shown posterior's count.
        best, chosen = scene_with_modes(settled, est.posterior, modes if shown and iteration == est.iteration
                                        else (), self.names())
        if chosen:
            note += "\n\nOther modes chosen:\n" + "\n".join(f"- {line}" for line in chosen)
        if est.ties:
            # The turns the depth scores about as well: a labeller checks these against the image or another view.
            note += ("\n\nThe depth hardly decides between these and the labels (check them; **Turn** or **Lay on "
                     "face** sets one):\n" + "\n".join(f"- {t.describe(run.problem)}" for t in est.ties))
        self.adopt(best, list(range(len(best))), "best", note)
        return not shown and est.posterior is not None

    def save(self, overwrite_original: bool) -> None:
        from workbench.label import frame as labelling

        self.labelled()
        run = self.on_show()
        ref, frame, problem = self.frame_ref, run.frame, run.problem
        if ref is None:
            raise InputError(None, f"labels are saved into the frame's BOP dataset, and {self.frame_ref_problem}")
        started = time.time()
        path = labelling.save_labels(Path(ref.dataset), frame.scene_id, frame.im_id, problem.camera.T_cam_world,
                                     self.labels, list(frame.object_ids), overwrite_original=overwrite_original,
                                     split=ref.split)
        note = labelling.kept_note(path, started) if overwrite_original else ""
        self.results.put(p.Saved("labels", str(path), note))

    def publish_errors(self, always: bool = False) -> None:
        """The best scene against the labels (every iteration while something is labelled; ``always`` after an
        edit, so that clearing the labels clears the table)."""
        from workbench.label import frame as labelling

        run = self.on_show()
        est, problem = run.estimator, run.problem
        if est is None or est.particles is None or not (always or any(T is not None for T in self.labels)):
            return
        if len(self.labels) != problem.n_objects:
            return
        errors = labelling.label_errors(problem, est.estimate, self.labels)
        self.results.put(p.LabelErrors(est.iteration, errors))

    def work(self) -> None:
        """What the latest label edit needs: the errors, and the heatmap if it is shown. Runs once the command
        queue is drained, so edits that arrived meanwhile were simply overwritten (dropped, not rendered)."""
        self.dirty = False
        if self.on_show().problem is None:
            return
        results = self.results
        try:
            self.publish_errors(always=True)
            if self.heatmap and any(T is not None for T in self.labels):
                scene, filled = self.scene(leave_out=True)
                pixels, residual = self.evaluators.explain(scene)
                results.put(p.LabelHeatmap(pixels.astype(np.float32), residual,
                                           float(pixels.sum(dtype=np.float64)), filled))
        except InputError as err:
            results.put(p.Failure("Labels", err.problem, err.path, topic="labels"))
        except CRASH_ERRORS:
            raise
        except Exception as err:  # noqa: BLE001 - a display computation must not stop the run
            log.error("label heatmap\n%s", traceback.format_exc())
            results.put(p.Failure(f"Label heatmap failed ({type(err).__name__})", str(err), topic="labels"))

    def reference_loglik(self) -> dict[str, float]:
        """The log-likelihoods of the known scenes, as given, for the Plots tab: {"truth_loglik": the frame's
        ground truth where it has one for every object, "label_loglik": the labels when every object is labelled},
        NaN where there is none. One render each, cached until the labels, frame or likelihood change."""
        if self.reference is None:
            run = self.on_show()
            frame, problem = run.frame, run.problem
            scenes = {"truth_loglik": truth_scene(frame, problem), "label_loglik": None}
            if self.labels and all(T is not None for T in self.labels):
                scenes["label_loglik"] = np.stack(self.labels)
            out = {}
            for key, scene in scenes.items():
                value = float("nan")
                if scene is not None and frame is not None and problem is not None:
                    pixels, _ = self.evaluators.explain(scene)
                    value = float(pixels.sum(dtype=np.float64))
                out[key] = value
            self.reference = out
        return self.reference

    def publish_truth(self) -> None:
        """The estimate against the dataset's ground truth, every iteration, where the frame has one: the run's
        settled answer with its posterior's confidences once it has one (what the 3D view draws, and what
        ``workbench estimate`` writes), else the best scene."""
        run = self.on_show()
        est, frame, problem = run.estimator, run.frame, run.problem
        if est is None or est.particles is None or frame is None or frame.gt_T_cam_obj is None:
            return
        from workbench.app.ui.run.truth import truth_rows

        if self.truth_points is None:
            self.truth_points = truth_points(problem)
        estimate = np.array(est.settled if est.answer_current else est.estimate, dtype=np.float64)
        rows = truth_rows(frame, problem, estimate, self.truth_points, est.current_posterior)
        self.results.put(p.TruthErrors(est.iteration, rows, estimate))
