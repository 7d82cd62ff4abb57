"""Sequences in the workbench's engine: a generated three-frame sequence loaded, its first frame
run, Next frame twice (tracked as `workbench track` tracks), a jump back showing the frame's own run, Next from
there stepping along the timeline, a session saving the position and a fresh engine restoring it, and bad input
(Next on the last frame, a next frame without depth) leaving the frame on show as it was. Real pybullet and
OpenGL; 320x240 and a few particles to stay quick."""

from __future__ import annotations

import numpy as np
import pytest
from inbox import Inbox

from workbench.app import protocol as p
from workbench.geometry import invert_pose
from workbench.score.metrics import position_error
from workbench.track.config import TrackConfig

pytestmark = pytest.mark.slow  # needs the engine: pybullet and OpenGL

CONFIG = dict(particles=16, iterations=2)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """Three frames of two touching boxes, the camera moving 5 degrees along an arc between frames."""
    from workbench.synth.sequence import make_sequences

    out = tmp_path_factory.mktemp("seq")
    make_sequences(out, ["touching"], 1, 3, seed=0, width=320, height=240, arc_deg=5.0, sensor="kinect-like")
    return out


def run_first_frame(engine, dataset) -> None:
    from workbench.inference.config import EstimatorConfig

    engine.handle(p.Load(p.Source(dataset=dataset, scene_id=0, im_id=0), EstimatorConfig(**CONFIG), "robust"))
    # Loaded, not yet run: the timeline does not call the frame estimated.
    assert [f.status for f in engine.results.of(p.SequenceState)[-1].frames] == ["not run yet"]
    while not engine.finished():
        engine.step()


def test_next_frame_tracks_jumps_back_and_a_session_keeps_the_position(sequence, tmp_path):
    from workbench.app.engine.engine import Engine

    inbox = Inbox()
    engine = Engine(inbox, workers=1)
    restored = None
    try:
        run_first_frame(engine, sequence)
        # The first frame's short run (16 particles, 2 iterations) need not find every box: at some seeds and on
        # some machines' package versions it leaves one ~20 cm off. Tracking may move an object its carried pose
        # does not explain, so stillness is asked only of the objects the first frame got right.
        gt = invert_pose(engine.problem.camera.T_cam_world)[None] @ engine.frame.gt_T_cam_obj
        found = np.array([position_error(gt[k], engine.estimator.estimate[k]) < 0.02 for k in range(len(gt))])
        assert found.any(), "the first frame's run found no object: nothing to track"
        state = inbox.of(p.SequenceState)[-1]
        assert state.scene_id == 0 and state.frame_ids == (0, 1, 2) and state.current == 0 and state.next_id == 1
        assert [f.status for f in state.frames] == ["estimated"] and np.isfinite(state.frames[0].positions).all()
        first = engine.estimator

        for im_id in (1, 2):
            engine.handle(p.NextFrame())
            assert not inbox.of(p.Failure), inbox.of(p.Failure)
            assert inbox.of(p.Loaded)[-1].keep_camera and engine.frame.im_id == im_id
        state = inbox.of(p.SequenceState)[-1]
        assert [f.im_id for f in state.frames] == [0, 1, 2] and state.current == 2 and state.next_id is None
        assert [f.status for f in state.frames[1:]] == ["tracked", "tracked"]
        assert [f.motion for f in state.frames] == ["", "given", "given"]
        assert state.reports and state.run_config.particles == TrackConfig().particles  # a tracked frame
        # A static scene seen from a moving camera: the objects found stay where they were in the sequence's table
        # frame.
        moved = np.linalg.norm(state.frames[2].positions - state.frames[0].positions, axis=1)
        assert moved[found].max() < 0.01, moved
        assert engine.evaluators.problem is engine.problem  # the pool evaluates the frame on show
        loaded = inbox.of(p.Loaded)
        assert loaded[-1].view.meshes is loaded[-2].view.meshes  # the same objects: not decimated again

        # Next on the last frame: a message, nothing changes.
        tracked = engine.estimator
        engine.handle(p.NextFrame())
        failure = inbox.of(p.Failure)[-1]
        assert failure.topic == "sequence" and "last of scene 0" in failure.problem
        assert engine.estimator is tracked and engine.frame.im_id == 2

        # Back to frame 0: its own run, not re-run; Next from it shows frame 1 as it was.
        n = len(inbox)
        engine.handle(p.ShowFrame(0))
        assert engine.estimator is first and engine.frame.im_id == 0 and inbox.of(p.SequenceState)[-1].current == 0
        assert inbox[n:] and not any(isinstance(m, p.Failure) for m in inbox[n:])
        snapshot = [m for m in inbox[n:] if isinstance(m, p.Snapshot)][-1]
        assert snapshot.report["iteration"] == first.iteration and snapshot.posterior is not None
        second = engine.sequence.frames[1].held.estimator
        engine.handle(p.NextFrame())
        assert engine.estimator is second and len(inbox.of(p.SequenceState)[-1].frames) == 3

        # A step on frame 1 changes its run: Next re-tracks frame 2 from it, the old frame 2 dropped.
        engine.step()
        engine.handle(p.NextFrame())
        assert engine.estimator is not tracked and engine.frame.im_id == 2
        state = inbox.of(p.SequenceState)[-1]
        assert [f.im_id for f in state.frames] == [0, 1, 2] and state.current == 2

        # A session keeps the position; a fresh engine restores it and Next goes on from there.
        engine.handle(p.ShowFrame(1))
        engine.handle(p.SaveSession(tmp_path, "seq"))
        assert inbox.of(p.Saved)[-1].kind == "session" and "frame 1 of a sequence of 3" in inbox.of(p.Saved)[-1].note
        second = Inbox()
        restored = Engine(second, workers=1)
        restored.handle(p.LoadSession(tmp_path / "seq.json"))
        assert not second.of(p.Failure), second.of(p.Failure)
        assert second.of(p.SessionRestored)[-1].config.particles == CONFIG["particles"]  # the panel's settings
        state = second.of(p.SequenceState)[-1]
        assert [f.im_id for f in state.frames] == [0, 1, 2] and state.current == 1
        assert [f.held for f in state.frames] == [False, True, False] and state.reports
        assert state.run_config is not None and state.run_config.particles == TrackConfig().particles
        restored.handle(p.ShowFrame(0))
        assert "not in the loaded session" in second.of(p.Failure)[-1].problem and restored.frame.im_id == 1
        restored.handle(p.NextFrame())
        state = second.of(p.SequenceState)[-1]
        assert restored.frame.im_id == 2 and state.current == 2 and state.frames[2].status == "tracked"
        assert len(second.of(p.Failure)) == 1
    finally:
        engine.close()
        if restored is not None:
            restored.close()


def test_a_next_frame_without_depth_is_a_message_and_the_frame_on_show_stays(sequence, tmp_path):
    import shutil

    from workbench.app.engine.engine import Engine

    data = tmp_path / "seq"
    shutil.copytree(sequence, data)
    (data / "test" / "000000" / "depth" / "000001.png").unlink()
    inbox = Inbox()
    engine = Engine(inbox, workers=1)
    try:
        engine.handle(p.NextFrame())  # nothing loaded yet
        assert inbox.of(p.Failure)[-1].topic == "sequence"
        run_first_frame(engine, data)
        run = engine.estimator
        engine.handle(p.NextFrame())
        failure = inbox.of(p.Failure)[-1]
        assert failure.topic == "sequence" and "000001.png" in (failure.path or "") + failure.problem, failure
        assert engine.estimator is run and engine.frame.im_id == 0
        assert engine.evaluators.problem is engine.problem
        engine.step()  # the run on show goes on
        assert engine.estimator.iteration == run.iteration and not inbox.of(p.SequenceState)[-1].frames[1:]
    finally:
        engine.close()


def test_a_sequence_record_round_trips_and_a_damaged_one_names_the_file(tmp_path):
    import json

    from workbench.errors import InputError
    from workbench.inference.config import EstimatorConfig
    from workbench.sessions.sequence_record import SequenceRecord, parse_record, record_json

    frames = [p.SequenceFrame(3, "estimated", 2.5, "", np.zeros((2, 3)), np.array([0.9, np.nan])),
              p.SequenceFrame(4, "1 object re-found", 0.8, "depth", np.ones((2, 3)), np.array([1.0, 0.5]))]
    record = SequenceRecord(frames, 4, EstimatorConfig(particles=16, iterations=2))
    stored = json.loads(json.dumps(record_json(record)))  # as a session file holds it (NaN included)
    back = parse_record(stored, tmp_path / "s.json", 2, 4)
    assert back.config == record.config and back.current == 4 and not any(f.held for f in back.frames)
    for a, b in zip(back.frames, frames):
        assert (a.im_id, a.status, a.seconds, a.motion) == (b.im_id, b.status, b.seconds, b.motion)
        assert np.array_equal(a.positions, b.positions) and np.array_equal(a.confidences, b.confidences,
                                                                           equal_nan=True)
    for damage, words in ((lambda d: d.update(current=3), "sequence.current"),
                          (lambda d: d["frames"][1].update(confidences=[1.0, 2.0]), "confidences must lie"),
                          (lambda d: d["frames"].reverse(), "increasing order"),
                          (lambda d: d["config"].pop("particles"), "missing settings"),
                          (lambda d: d.pop("frames"), "malformed sequence entry")):
        bad = json.loads(json.dumps(stored))
        damage(bad)
        with pytest.raises(InputError) as err:
            parse_record(bad, tmp_path / "s.json", 2, 4)
        assert err.value.path.endswith("s.json") and words in err.value.problem, err.value.problem
