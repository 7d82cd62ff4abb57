"""The frame's label files, on the engine's side: saving the labels, listing the backups of the scene's
scene_gt.json and restoring one (the file work is ``workbench.label.frame``'), and reading the frame's ground truth
again whenever one of these wrote scene_gt.json, so that the truth table and the Plots tab's reference score
against the truth as it is now on disk.

Like the other helpers, ``act`` changes none of the engine's fields: it returns the frame on show with its new
ground truth, and the engine puts that on show (``Engine.reload_truth``).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from workbench.app import protocol as p
from workbench.app.engine.labels import FrameLabels
from workbench.app.engine.on_show import RunOnShow
from workbench.errors import InputError


def act(cmd: p.SaveLabels | p.ListBackups | p.RestoreBackup, labels: FrameLabels, run: RunOnShow):
    """Do ``cmd`` -> the frame on show (``scene.Frame``) with its ground truth read again where scene_gt.json was
    written, else None. Bad input raises InputError naming the file, with nothing written."""
    from workbench.label import frame as labelling

    if isinstance(cmd, p.SaveLabels):
        labels.save(cmd.overwrite_original)
        if not cmd.overwrite_original:
            return None
    dataset, split = where(labels)
    scene_id = run.frame.scene_id
    if isinstance(cmd, p.RestoreBackup):
        path, kept = labelling.restore_backup(dataset, scene_id, cmd.name, split)
        note = f"restored from `{cmd.name}`; " + (f"the one it replaced was kept as `{kept.name}`" if kept else
                                                   "there was no scene_gt.json to keep")
        labels.results.put(p.Saved("ground truth", str(path), note))
    backups = labelling.list_backups(dataset, scene_id, split)
    original = labelling.labels_path(dataset, scene_id, split).with_name(labelling.ORIGINAL_FILE)
    labels.results.put(p.Backups(str(original), [(b.path.name, f"{b.time:%Y-%m-%d %H:%M:%S}") for b in backups]))
    return None if isinstance(cmd, p.ListBackups) else reread_truth(labels, run, dataset, split)


def where(labels: FrameLabels) -> tuple[Path, str | None]:
    """The frame's dataset folder and split; InputError when the frame is not from a BOP dataset."""
    if labels.frame_ref is None:
        raise InputError(None, f"scene_gt.json backups belong to the frame's BOP dataset, and "
                               f"{labels.frame_ref_problem}")
    return Path(labels.frame_ref.dataset), labels.frame_ref.split


def reread_truth(labels: FrameLabels, run: RunOnShow, dataset: Path, split: str | None):
    """The frame on show with its ground truth as scene_gt.json now has it (the server is sent it to draw); None,
    with a message, where the file no longer gives this frame a ground truth."""
    from workbench.geometry import invert_pose
    from workbench.io import bop

    frame, problem = run.frame, run.problem
    try:
        fresh = bop.load_frame(dataset, frame.scene_id, frame.im_id, split, object_ids=list(frame.object_ids))
    except InputError as err:
        labels.results.put(p.Failure("Ground truth: not read again", err.problem, err.path, topic="labels"))
        return None
    frame = replace(frame, gt_T_cam_obj=fresh.gt_T_cam_obj)
    labels.reference = None  # the Plots tab's truth log-likelihood, of the old truth
    gt = None if frame.gt_T_cam_obj is None else invert_pose(problem.camera.T_cam_world)[None] @ frame.gt_T_cam_obj
    labels.results.put(p.TruthReloaded(gt))
    return frame
