"""Sequence labels in the workbench's engine (issue 68), without a browser: the labels read back from per-frame
poses (first, last, moves), each frame's camera pose in the sequence's table frame (given per frame, or from the
camera's world poses), the panel's marks, and the engine's commands on a generated four-frame sequence: check,
propagate (every frame, from a frame on), show a frame the timeline had not processed, end a label, fit to all
frames, save (beside the ground truth, or over it with a backup) and read the saved labels back; bad input told
beside the buttons with nothing changed."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from inbox import Inbox

from workbench.app import protocol as p
from workbench.errors import InputError
from workbench.geometry import make_pose, rot_z
from workbench.label.sequence import from_frame_poses


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """Four frames of two touching boxes, the camera moving 6 degrees along an arc between frames (no rendering:
    the generator ray-casts its depth)."""
    from workbench.synth.sequence import make_sequences

    out = tmp_path_factory.mktemp("label_seq")
    make_sequences(out, ["touching"], 1, 4, seed=0, width=320, height=240, arc_deg=6.0, sensor="kinect-like")
    return out


# ------------------------------------------------------------------------------------------------------------------
# Fast: reading labels back, camera poses, the panel's marks


def test_labels_read_back_frame_by_frame_keep_first_last_and_moves():
    cams = {i: np.eye(4) for i in range(5)}
    A, B = make_pose(np.eye(3), [0.1, 0, 0]), make_pose(rot_z(np.radians(30)), [0.2, 0, 0])
    jitter = make_pose(np.eye(3), [0.1 + 2e-4, 0, 0])  # a saved file's rounding: no move
    poses = {0: [A, None], 1: [jitter, B], 2: [A, B], 3: [B, B], 4: [B, None]}
    labels = from_frame_poses(7, cams, [3, 5], poses)
    a, b = labels.objects
    assert (a.first, a.last, sorted(a.moves)) == (None, None, [3]) and np.allclose(a.pose_at(2), A)
    assert np.allclose(a.pose_at(4), B)
    assert (b.first, b.last, b.moves) == (1, 3, {}) and b.pose_at(0) is None and b.pose_at(4) is None
    with pytest.raises(InputError, match="no frame of scene 7"):
        from_frame_poses(7, cams, [3, 5], {i: [A, None] for i in range(5)})


def test_camera_poses_from_the_frames_or_the_cameras_world_poses(sequence, tmp_path):
    from workbench.app.engine.sequence_cameras import sequence_cameras
    from workbench.io import bop

    given = {i: bop.load_frame(sequence, 0, i).camera.T_cam_world for i in range(4)}
    region = (np.array([-0.3, -0.3]), np.array([0.3, 0.3]))
    cams = sequence_cameras(sequence, 0, None, [0, 1, 2, 3], {0: given[0]}, region)
    assert all(np.allclose(cams[i], given[i]) for i in range(4))
    # Without a table pose per frame: the first frame's moved by the camera's world poses, the same table frame.
    copy = tmp_path / "copy"
    shutil.copytree(sequence, copy)
    path = copy / "test" / "000000" / "scene_camera.json"
    cameras = json.loads(path.read_text())
    for entry in cameras.values():
        del entry["cam_R_w2c"], entry["cam_t_w2c"]
    path.write_text(json.dumps(cameras))
    cams = sequence_cameras(copy, 0, None, [0, 1, 2, 3], {0: given[0]}, region)
    assert all(np.allclose(cams[i], given[i], atol=1e-6) for i in range(4))
    with pytest.raises(InputError, match="no frame of the sequence is processed"):
        sequence_cameras(copy, 0, None, [0, 1], {}, region)


def test_the_timeline_marks_each_frame_by_its_worst_object():
    from workbench.app.ui.labelling.sequence_labels import grade, option, summary_markdown, table_markdown

    def frame(im, worst, flagged):
        checks = [{"obj_id": 1, "agree": worst or 0.0, "through": 0.6, "front": 0.0, "flagged": flagged,
                   "reason": "seen past"}]
        return p.LabelledFrame(im, worst, flagged, checks)

    frames = [frame(0, 0.95, False), frame(1, 0.6, False), frame(2, 0.2, True), frame(3, None, False)]
    assert [grade(f) for f in frames] == ["good", "fair", "flagged", "unchecked"]
    assert [option(f) for f in frames] == ["0 ✓", "1 ~", "2 ✗", "3 ·"]
    msg = p.SequenceLabelState(0, frames)
    assert "**1 flagged** (2)" in summary_markdown(msg)
    table = table_markdown(msg, 2, ["box"])
    row = next(r for r in table.splitlines() if "| 2 |" in r)
    assert row.startswith("| ▶ |") and "rgb(215,45,45)" in row and "20% (seen past)" in row


# ------------------------------------------------------------------------------------------------------------------
# The engine's commands (slow: pybullet and OpenGL)


def state(inbox) -> p.SequenceLabelState:
    return inbox.of(p.SequenceLabelState)[-1]


def flagged(inbox) -> list[int]:
    return [f.im_id for f in state(inbox).frames if f.flagged]


def failed(inbox, n_before: int) -> list[p.Failure]:
    return [f for f in inbox.of(p.Failure)[n_before:] if f.topic == "sequence labels"]


def moved(T: np.ndarray, dx: float) -> np.ndarray:
    out = np.array(T, dtype=np.float64)
    out[0, 3] += dx
    return out


def run_first_frame(engine, data, iterations: int) -> None:
    """Load frame 0 of the copied sequence ``data`` and run the estimator on it to the end."""
    from workbench.inference.config import EstimatorConfig

    engine.handle(p.Load(p.Source(dataset=data, scene_id=0, im_id=0),
                         EstimatorConfig(particles=32, iterations=iterations), "robust"))
    while not engine.finished():
        engine.step()


@pytest.mark.slow
def test_check_propagate_show_end_fit_save_and_read_back(sequence, tmp_path):
    from workbench.app.engine.engine import Engine

    data = tmp_path / "data"
    shutil.copytree(sequence, data)
    scene = data / "test" / "000000"
    inbox = Inbox()
    engine = Engine(inbox, workers=1)
    try:
        run_first_frame(engine, data, 4)
        labels = engine.labels

        # Bad input first: told beside the buttons, nothing started.
        n = len(inbox.of(p.Failure))
        engine.handle(p.CheckSequenceLabels("current"))  # nothing labelled yet
        engine.handle(p.PropagateLabel(0))
        engine.handle(p.UseBestAsLabel())
        engine.handle(p.CheckSequenceLabels("current", "2:9"))
        engine.handle(p.CheckSequenceLabels("saved"))
        problems = [f.problem for f in failed(inbox, n)]
        assert len(problems) == 4, problems
        assert "label every object" in problems[0] and "start them first" in problems[1]
        assert "no frame 9" in problems[2] and "no sequence labels were saved" in problems[3]
        assert engine.sequence_labels.labels is None
        start = [T.copy() for T in labels.labels]

        # Checked on every frame: the estimate agrees with each frame's depth.
        engine.handle(p.CheckSequenceLabels("current"))
        assert [f.im_id for f in state(inbox).frames] == [0, 1, 2, 3] and flagged(inbox) == []
        assert all(f.worst > 0.9 for f in state(inbox).frames)

        # One label 3 cm off, propagated to every frame: every frame flagged.
        engine.handle(p.SetLabels(tuple([moved(start[0], 0.03), start[1]])))
        engine.handle(p.PropagateLabel(0))
        assert flagged(inbox) == [0, 1, 2, 3]
        assert all(not f.checks[1]["flagged"] for f in state(inbox).frames)  # the other box is still right

        # Frame 2, which the timeline had not processed: a fresh run on it, the sequence's labels in the Label tab.
        engine.handle(p.ShowLabelledFrame(2))
        assert engine.frame.im_id == 2 and engine.estimator.iteration < 0
        assert [f.entry.im_id for f in engine.sequence.frames] == [0, 2]
        assert engine.sequence.frames[1].entry.status == "labelling"
        shown = inbox.of(p.Labels)[-1]
        assert shown.reason == "sequence" and np.allclose(shown.labels[0], moved(start[0], 0.03), atol=1e-9)

        # Put back from this frame on: the frames before stay flagged.
        engine.handle(p.SetLabels(tuple([start[0], start[1]])))
        engine.handle(p.PropagateLabel(0, from_here=True))
        assert flagged(inbox) == [0, 1]
        assert sorted(engine.sequence_labels.labels.objects[0].moves) == [2]
        assert 2 in engine.sequence_labels.labels.checked

        # Back on every frame, then the first box's label ended on frame 1: not checked after it.
        engine.handle(p.PropagateLabel(0))
        assert flagged(inbox) == []
        engine.handle(p.EndSequenceLabel(0, 1))
        assert engine.sequence_labels.labels.objects[0].last == 1
        assert [f.checks[0]["checked"] for f in state(inbox).frames] == [True, True, False, False]
        assert inbox.of(p.Labels)[-1].labels[0] is None  # frame 2, on show: the box has no label any more

        # A label moving is not fitted; a still one is: 3 cm off on every frame, fitted back.
        engine.handle(p.ShowLabelledFrame(0))
        assert engine.frame.im_id == 0
        engine.sequence_labels.labels.objects[0].last = None
        engine.handle(p.SetLabels(tuple([moved(start[0], 0.03), start[1]])))
        engine.handle(p.PropagateLabel(0))
        assert flagged(inbox) == [0, 1, 2, 3]
        engine.handle(p.FitSequenceLabels())
        assert flagged(inbox) == [], state(inbox).note
        fitted = engine.sequence_labels.labels.objects[0].T_world_obj
        assert np.linalg.norm(fitted[:3, 3] - start[0][:3, 3]) < 0.01
        assert inbox.of(p.SequenceLabelProgress)  # a long fit says what it does

        # Saved beside the ground truth, which stays as it was; read back as saved.
        truth = (scene / "scene_gt.json").read_bytes()
        engine.handle(p.SaveSequenceLabels())
        assert inbox.of(p.Saved)[-1].kind == "sequence labels"
        assert (scene / "scene_gt.json").read_bytes() == truth
        provenance = json.loads((scene / "label_provenance.json").read_text())
        assert provenance["frames"]["0"]["source"] == "checked" and not provenance["frames"]["0"]["flagged"]
        saved = [o.T_world_obj.copy() for o in engine.sequence_labels.labels.objects]
        engine.handle(p.SetLabels(tuple([moved(start[0], 0.05), start[1]])))
        engine.handle(p.PropagateLabel(0))
        engine.handle(p.CheckSequenceLabels("saved"))
        assert flagged(inbox) == []
        back = engine.sequence_labels.labels
        assert all(np.allclose(o.T_world_obj, T, atol=1e-6) and not o.moves for o, T in zip(back.objects, saved))
        assert np.allclose(inbox.of(p.Labels)[-1].labels[0], saved[0], atol=1e-6)

        # Over the scene's own ground truth only when asked: a backup kept, the truth read again.
        engine.handle(p.SaveSequenceLabels(overwrite_original=True))
        assert "the original was kept" in inbox.of(p.Saved)[-1].note
        assert list(scene.glob("scene_gt.json.bak-*")) and inbox.of(p.TruthReloaded)
        assert not failed(inbox, 0)[4:], failed(inbox, 0)
    finally:
        engine.close()


@pytest.mark.slow
def test_a_session_keeps_the_sequence_labels_written_or_not(sequence, tmp_path):
    """Sequence labels are the user's work: loading another frame while they hold changes that nothing saved is
    refused once; a session saved while they are on hand (none written to the dataset) brings them back on load,
    every frame checked again; loading a session saved with none leaves none. A corrupt labels entry is refused,
    naming the session file."""
    from workbench.app.engine.engine import Engine
    from workbench.inference.config import EstimatorConfig

    data = tmp_path / "data"
    shutil.copytree(sequence, data)
    inbox = Inbox()
    engine = Engine(inbox, workers=1)
    try:
        run_first_frame(engine, data, 2)
        engine.handle(p.SaveSession(tmp_path / "sessions", "none"))
        engine.handle(p.UseBestAsLabel())
        start = [T.copy() for T in engine.labels.labels]
        engine.handle(p.CheckSequenceLabels("current"))
        engine.handle(p.SetLabels(tuple([moved(start[0], 0.03), start[1]])))
        engine.handle(p.PropagateLabel(0))
        kept = engine.sequence_labels.labels
        assert flagged(inbox) == [0, 1, 2, 3]
        # Unsaved, they are not dropped by loading another frame unseen: refused once, with the way out.
        with pytest.raises(InputError, match="not saved.*press Load again"):  # the engine's loop tells it
            engine.handle(p.Load(p.Source(dataset=data, scene_id=0, im_id=1), EstimatorConfig(particles=32),
                                 "robust"))
        assert engine.frame.im_id == 0 and engine.sequence_labels.labels is kept
        engine.handle(p.SaveSession(tmp_path / "sessions", "labelled"))
        assert [s.kind for s in inbox.of(p.Saved)] == ["session", "session"]
        engine.handle(p.Load(p.Source(dataset=data, scene_id=0, im_id=1), EstimatorConfig(particles=32), "robust"))
        assert engine.frame.im_id == 1 and engine.sequence_labels.labels is None  # the session holds them

        engine.handle(p.LoadSession(tmp_path / "sessions" / "none.json"))
        assert engine.sequence_labels.labels is None
        engine.handle(p.LoadSession(tmp_path / "sessions" / "labelled.json"))
        back = engine.sequence_labels.labels
        assert back is not None and back.frames == kept.frames and back.checked == kept.checked
        assert all(np.allclose(o.T_world_obj, k.T_world_obj) for o, k in zip(back.objects, kept.objects))
        assert flagged(inbox) == [0, 1, 2, 3] and "Restored from the session" in state(inbox).note

        path = tmp_path / "sessions" / "labelled.json"
        doc = json.loads(path.read_text())
        doc["sequence"]["labels"]["objects"][0]["T_world_obj"] = [1.0] * 16
        path.write_text(json.dumps(doc))
        n = len(inbox.of(p.Failure))
        engine.handle(p.LoadSession(path))
        problems = [f.problem for f in inbox.of(p.Failure)[n:]]
        assert problems and "sequence.labels.objects[0].T_world_obj" in problems[-1], problems
        assert engine.sequence_labels.labels is back  # the labels on hand stay
    finally:
        engine.close()
