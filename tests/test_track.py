"""`workbench track` on generated sequences (``make-scenes --sequence``): a static sequence tracked end to end, an
object pushed between two frames re-found, a frame whose objects all moved re-initialised, a frame without depth
and an object taken out reported as lost and recovered, a still object kept still, the camera's motion registered
from the depth, a mug's hidden handle decided once the camera sees it. Real pybullet and OpenGL; 320x240 to stay
quick."""

import numpy as np
import pytest
from PIL import Image

from workbench.cli import main
from workbench.errors import InputError
from workbench.inference.config import EstimatorConfig
from workbench.inference.search.track_search import settle_each
from workbench.io import bop
from workbench.io.results import read_results_csv
from workbench.problem.support import estimate_support
from workbench.score.metrics import is_right
from workbench.score.scoring import score_results
from workbench.synth.sequence import Push, TakeOut, make_sequences
from workbench.track.config import TrackConfig
from workbench.track.motion import depth_motion, given_motion, read_world_poses
from workbench.track.sequence import Tracker, track_frames

pytestmark = pytest.mark.slow

FIRST = ["--particles", "100", "--iterations", "8", "--workers", "1"]  # the first frame's budget: two boxes


def _sequence(out, frames, push=None, arc_deg=4.0, take_out=None):
    make_sequences(out, ["touching"], 1, frames, seed=0, width=320, height=240, arc_deg=arc_deg, push=push,
                   take_out=take_out, sensor="kinect-like")
    return out


def _track(data, frames, object_ids=None):
    tracker = Tracker(data, 0, frames, EstimatorConfig(particles=100, iterations=8), TrackConfig(), workers=1,
                      object_ids=object_ids)
    try:
        return track_frames(tracker, frames, set(), lambda result: None)
    finally:
        tracker.close()


def _right(data, im_id, rows):
    """Per object of the frame (its scene_gt.json), whether its top row is right."""
    frame = bop.load_frame(data, 0, im_id)
    models = bop.load_models(data, frame.object_ids)
    top = {}
    for r in rows:
        if r.obj_id not in top or r.score > top[r.obj_id].score:
            top[r.obj_id] = r
    return [bool(is_right(T, top[o].T_cam_obj, models[o].symmetries)) if o in top else False
            for o, T in zip(frame.object_ids, frame.gt_T_cam_obj)]


def test_a_static_sequence_is_tracked_with_every_object_right(tmp_path, capsys):
    data = _sequence(tmp_path / "seq", 3)
    out = tmp_path / "results.csv"
    assert main(["track", str(data), "--scene", "0", "--out", str(out), "--posterior", str(tmp_path / "p.json"),
                 *FIRST]) == 0
    err = capsys.readouterr().err
    assert "scene 0 frame 1: tracked in" in err and "scene 0 frame 2: tracked in" in err
    frames = score_results(data, read_results_csv(out))
    assert [f.im_id for f in frames] == [0, 1, 2] and all(f.right for f in frames)

    # Stopped after frame 1 and resumed: frame 2 gets the rows the undisturbed run gave it (all but the time),
    # since the frames kept are tracked again to carry on from them, unwritten.
    whole = out.read_text().splitlines()
    out.write_text("\n".join(line for line in whole if line.split(",")[1] != "2") + "\n")
    assert main(["track", str(data), "--scene", "0", "--out", str(out), "--resume", *FIRST]) == 0
    err = capsys.readouterr().err
    assert "scene 0 frame 1: kept from before; tracked again" in err and "scene 0 frame 2: tracked in" in err
    untimed = [line.rsplit(",", 1)[0] for line in out.read_text().splitlines()]
    assert untimed == [line.rsplit(",", 1)[0] for line in whole] and len(untimed) > 3


def test_a_pushed_object_is_refound(tmp_path):
    data = _sequence(tmp_path / "seq", 2, push=Push(frame=1, distance=0.06))
    tracker = Tracker(data, 0, [0, 1], EstimatorConfig(particles=100, iterations=8), TrackConfig(), workers=1)
    try:
        results = track_frames(tracker, [0, 1], set(), lambda result: None)
    finally:
        tracker.close()
    frame = bop.load_frame(data, 0, 1)
    pushed = 0  # make_sequences pushes the first object that stands alone: the base of the touching pair
    estimate = next(r.T_cam_obj for r in results[1].rows if r.obj_id == frame.object_ids[pushed])
    assert results[1].status == "1 object re-found"
    symmetries = bop.load_models(data, [frame.object_ids[pushed]])[frame.object_ids[pushed]].symmetries
    assert is_right(frame.gt_T_cam_obj[pushed], estimate, symmetries)


def test_a_tracked_frame_steps_few_particles_and_a_re_search_at_least_the_lost_count():
    base, track = EstimatorConfig(), TrackConfig()
    assert track.frame_config(base, lost=False).particles == track.particles < track.lost_particles
    assert track.frame_config(base, lost=True).particles == track.lost_particles
    assert TrackConfig(particles=100).frame_config(base, lost=True).particles == 100
    with pytest.raises(InputError, match="lost_particles"):
        TrackConfig(lost_particles=0).validate()


def test_a_frame_whose_objects_all_moved_is_reinitialised(tmp_path):
    data = _sequence(tmp_path / "seq", 2, arc_deg=0.0)
    # Frame 1: frame 0's depth shifted 60 pixels sideways, the camera as it was: every object 15-20 cm away.
    path = data / "test" / "000000" / "depth" / "000001.png"
    depth = np.asarray(Image.open(data / "test" / "000000" / "depth" / "000000.png"))
    Image.fromarray(np.roll(depth, 60, axis=1)).save(path)
    tracker = Tracker(data, 0, [0, 1], EstimatorConfig(particles=100, iterations=8), TrackConfig(), workers=1)
    try:
        results = track_frames(tracker, [0, 1], set(), lambda result: None)
    finally:
        tracker.close()
    assert results[1].status == "re-initialised"


def test_a_still_object_keeps_its_last_answer_unless_the_depth_clearly_moves_it():
    last = np.repeat(np.eye(4)[None], 2, axis=0)
    found = last.copy()
    found[:, 0, 3] = 0.05  # this frame's search put both 5 cm along x, where the depth is worse
    best = np.array([0.001, 0.006])  # where the depth wants each object: 1 mm off (noise), 6 mm off (moved)
    gain = np.array([5.0, 100.0])  # what each gains there over its last answer

    def score(scenes):  # log-likelihood: each object's gain, falling off within 0.5 mm of where the depth wants it
        x = scenes[:, :, 0, 3]
        return np.sum(gain * np.clip(1.0 - np.abs(x - best) / 0.0005, 0.0, 1.0) - 1000.0 * np.abs(x - best), axis=1)

    scene, _, _ = settle_each(found, last, score, max_shift_m=0.015, max_turn_deg=12.0, margin=30.0)
    assert np.array_equal(scene[0], last[0]) and abs(scene[1, 0, 3] - 0.006) < 0.001


def test_camera_motion_from_the_depth_matches_the_given_motion(tmp_path):
    data = _sequence(tmp_path / "seq", 2, arc_deg=2.0)  # the camera moves 2 cm and turns 2 degrees
    world = read_world_poses(data / "test" / "000000")
    first = bop.load_frame(data, 0, 0)
    camera, table = estimate_support(first)
    M = depth_motion(first, bop.load_frame(data, 0, 1), camera.T_cam_world, (table.region_min, table.region_max))
    error = np.linalg.inv(given_motion(world[0], world[1])) @ M
    angle = np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))
    assert np.linalg.norm(error[:3, 3]) < 0.01 and angle < 2.0


def _modes_right(data, im_id, rows):
    """A one-object frame's modes, most likely first: whether each is right."""
    frame = bop.load_frame(data, 0, im_id)
    symmetries = bop.load_models(data, frame.object_ids)[frame.object_ids[0]].symmetries
    return [bool(is_right(frame.gt_T_cam_obj[0], r.T_cam_obj, symmetries))
            for r in sorted(rows, key=lambda r: -r.score)]


def test_a_frame_without_depth_is_lost_its_posterior_carried_and_the_next_frame_recovers(tmp_path):
    data = _sequence(tmp_path / "seq", 3)
    path = data / "test" / "000000" / "depth" / "000001.png"
    Image.fromarray(np.zeros_like(np.asarray(Image.open(path)))).save(path)  # a dropped frame: no reading at all
    results = _track(data, [0, 1, 2])
    carried = [r.score for r in results[0].rows] == [r.score for r in results[1].rows]  # the posterior unchanged
    assert ([r.status for r in results], carried, _right(data, 2, results[2].rows)) == (
        ["estimated", "lost: no depth", "recovered"], True, [True, True])


def test_an_object_taken_out_is_lost_and_recovered_when_put_back(tmp_path):
    data = _sequence(tmp_path / "seq", 3, take_out=TakeOut(frame=1, back=2))
    # The sequence's objects, as a recognition system that knows the scene reports them (frame 1's scene_gt.json
    # leaves out the one taken out).
    results = _track(data, [0, 1, 2], object_ids=bop.load_frame(data, 0, 0).object_ids)
    assert ([r.status for r in results], _right(data, 2, results[2].rows)) == (
        ["estimated", "1 object still lost", "1 object recovered"], [True, True])


def test_a_hidden_handle_keeps_its_modes_until_the_camera_sees_it(tmp_path):
    # A mug alone, its handle hidden behind its body on frames 0-2 and in view from frame 3 as the camera moves.
    make_sequences(tmp_path / "seq", ["handle_hidden"], 1, 5, seed=0, width=320, height=240, handle=3,
                   sensor="kinect-like")
    results = _track(tmp_path / "seq", [0, 1, 2, 3, 4])
    seen = []
    for i, result in enumerate(results):
        right = _modes_right(tmp_path / "seq", i, result.rows)
        top = max(r.score for r in result.rows)
        seen.append((len(right) > 1 and any(right) and top <= 0.6) if i < 3 else (top > 0.9 and right[0]))
    # Hidden: several modes, the truth among them, none sure (each view's gaps against the estimate as carried, not
    # as settled: against the settled one the top mode reached 0.75); shown: one mode above 0.9, the truth.
    assert seen == [True] * 5


def test_a_hidden_object_keeps_its_hiding_region_while_it_stays_hidden(tmp_path):
    """The box behind the box in front is unseen on every frame of the arc: each frame's line names its region, the
    first frame's from the posterior sweep, the tracked ones' carried and scored again on their view."""
    make_sequences(tmp_path / "seq", ["occluded"], 1, 3, seed=1, width=320, height=240, arc_deg=4.0,
                   sensor="kinect-like")
    results = _track(tmp_path / "seq", [0, 1, 2])
    assert [r.status for r in results] == ["estimated", "tracked", "tracked"]
    assert all("(hidden: one of" in r.line for r in results), [r.line for r in results]
