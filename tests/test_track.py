"""`workbench track` on generated sequences (``make-scenes --sequence``): a static sequence tracked end to end, an
object pushed between two frames re-found, a frame whose objects all moved re-initialised, a still object kept
still, the camera's motion registered from the depth. Real pybullet and OpenGL; 320x240 to stay quick."""

import numpy as np
import pytest
from PIL import Image

from workbench.bench.scoring import score_results
from workbench.cli import main
from workbench.inference.config import EstimatorConfig
from workbench.io import bop
from workbench.metrics import is_right
from workbench.support import estimate_support
from workbench.synth.sequence import Push, make_sequences
from workbench.inference.track_search import keep_still
from workbench.track.config import TrackConfig
from workbench.track.motion import depth_motion, given_motion, read_world_poses
from workbench.track.sequence import Tracker, track_frames

pytestmark = pytest.mark.slow

FIRST = ["--particles", "100", "--iterations", "8", "--workers", "1"]  # the first frame's budget: two boxes


def _sequence(out, frames, push=None, arc_deg=4.0):
    make_sequences(out, ["touching"], 1, frames, seed=0, width=320, height=240, arc_deg=arc_deg, push=push)
    return out


def test_a_static_sequence_is_tracked_with_every_object_right(tmp_path, capsys):
    data = _sequence(tmp_path / "seq", 3)
    out = tmp_path / "results.csv"
    assert main(["track", str(data), "--scene", "0", "--out", str(out), "--posterior", str(tmp_path / "p.json"),
                 *FIRST]) == 0
    err = capsys.readouterr().err
    assert "scene 0 frame 1: tracked in" in err and "scene 0 frame 2: tracked in" in err
    frames = score_results(data, bop.read_results_csv(out))
    assert [f.im_id for f in frames] == [0, 1, 2] and all(f.right for f in frames)


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
    settled = last.copy()
    settled[:, 0, 3] = [0.001, 0.02]  # object 0 moved by noise, object 1 by much more
    gain = np.array([5.0, 100.0])  # what each object's settled pose gains over its last answer

    def score(scenes):  # log-likelihood: the gains of the objects at their settled poses
        return np.array([float(np.sum(gain * (s[:, 0, 3] != 0))) for s in scenes])

    scene, loglik, _ = keep_still(settled, score(settled[None])[0], last, score, margin=30.0)
    assert np.array_equal(scene[0], last[0]) and np.array_equal(scene[1], settled[1]) and loglik == 100.0


def test_camera_motion_from_the_depth_matches_the_given_motion(tmp_path):
    data = _sequence(tmp_path / "seq", 2, arc_deg=2.0)  # the camera moves 2 cm and turns 2 degrees
    world = read_world_poses(data / "test" / "000000")
    first = bop.load_frame(data, 0, 0)
    camera, table = estimate_support(first)
    M = depth_motion(first, bop.load_frame(data, 0, 1), camera.T_cam_world, (table.region_min, table.region_max))
    error = np.linalg.inv(given_motion(world[0], world[1])) @ M
    angle = np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))
    assert np.linalg.norm(error[:3, 3]) < 0.01 and angle < 2.0
