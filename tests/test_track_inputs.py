"""`workbench track`'s input checks, the camera's motion from given poses and the status words: no physics, no
rendering (the fast tier). The tracking itself is tested in test_track.py."""

import json

import numpy as np
import pytest

from workbench.cli import main
from workbench.errors import InputError
from workbench.geometry import invert_pose, make_pose, rot_x, rot_z
from workbench.io import bop
from workbench.track.frames import sequence_frames, sequence_world
from workbench.track.lost import lost_objects, status_words
from workbench.track.motion import given_motion, read_world_poses


def _sequence(tmp_path, ids, world=True, depth_missing=()):
    """A scene folder with ``ids`` in scene_camera.json, a depth PNG each (but ``depth_missing``) and, with
    ``world``, each frame's camera pose in scene_camera_world.json."""
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    for i in ids:
        bop.save_frame(tmp_path, 1, i, np.full((240, 320), 0.8), K)
        if i in depth_missing:
            (tmp_path / "test" / "000001" / "depth" / f"{i:06d}.png").unlink()
    if world:
        poses = {str(i): {"R_w2c": np.eye(3).ravel().tolist(), "t_w2c": [10.0 * i, 0.0, 900.0]} for i in ids}
        (tmp_path / "test" / "000001" / "scene_camera_world.json").write_text(json.dumps(poses))
    return tmp_path


def test_frames_default_to_the_whole_scene_and_take_a_range(tmp_path):
    _sequence(tmp_path, [1, 2, 3, 4])
    assert sequence_frames(tmp_path, 1, None, None) == [1, 2, 3, 4]
    assert sequence_frames(tmp_path, 1, None, "2:3") == [2, 3]


@pytest.mark.parametrize("frames, words", [("1:9", "no frame 9"), ("3:2", "A <= B"), ("x", "must be A:B")])
def test_a_frame_range_that_does_not_exist_is_refused(tmp_path, frames, words):
    _sequence(tmp_path, [1, 2, 3])
    with pytest.raises(InputError, match=words) as err:
        sequence_frames(tmp_path, 1, None, frames)
    assert err.value.path == "--frames"


def test_a_missing_frame_in_the_middle_is_refused(tmp_path):
    _sequence(tmp_path, [1, 2, 4, 5])
    with pytest.raises(InputError, match="frame 3 is missing between 1 and 5") as err:
        sequence_frames(tmp_path, 1, None, None)
    assert err.value.path.endswith("scene_camera.json")


def test_a_missing_depth_image_is_refused(tmp_path):
    _sequence(tmp_path, [1, 2, 3], depth_missing=(2,))
    with pytest.raises(InputError, match="no depth") as err:
        sequence_frames(tmp_path, 1, None, None)
    assert err.value.path.endswith("000002.png")


def test_given_motion_needs_scene_camera_world(tmp_path):
    _sequence(tmp_path, [1, 2], world=False)
    assert sequence_world(tmp_path, 1, None, "auto", [1, 2]) is None  # auto: registered from the depth instead
    with pytest.raises(InputError, match="--motion depth") as err:
        sequence_world(tmp_path, 1, None, "given", [1, 2])
    assert err.value.path.endswith("scene_camera_world.json")


def test_a_frame_without_a_camera_pose_is_refused(tmp_path):
    _sequence(tmp_path, [1, 2, 3])
    path = tmp_path / "test" / "000001" / "scene_camera_world.json"
    poses = json.loads(path.read_text())
    del poses["2"]
    path.write_text(json.dumps(poses))
    with pytest.raises(InputError, match="frame 2 has no camera pose"):
        sequence_world(tmp_path, 1, None, "auto", [1, 2, 3])


def test_a_malformed_camera_pose_names_the_file_and_the_frame(tmp_path):
    _sequence(tmp_path, [1, 2])
    path = tmp_path / "test" / "000001" / "scene_camera_world.json"
    path.write_text(json.dumps({"1": {"R_w2c": [1, 0, 0], "t_w2c": [0, 0, 0]}}))
    with pytest.raises(InputError, match="image 1") as err:
        read_world_poses(path.parent)
    assert err.value.path == str(path)


def test_the_command_line_refuses_bad_input_with_exit_code_2(tmp_path, capsys):
    _sequence(tmp_path, [1, 2], world=False)
    code = main(["track", str(tmp_path), "--scene", "1", "--motion", "given", "--out", str(tmp_path / "r.csv")])
    assert code == 2 and "scene_camera_world.json: not found" in capsys.readouterr().err
    assert not (tmp_path / "r.csv").exists()


def _depth_of_frame(tmp_path, i, depth_m, size=(240, 320)):
    """Frame ``i``'s depth image replaced by ``depth_m`` metres everywhere (save_frame's depth_scale 0.1: PNG units
    are 0.1 mm)."""
    from PIL import Image

    raw = np.full(size, depth_m * 10_000.0).clip(0, 65535).astype(np.uint16)
    Image.fromarray(raw).save(tmp_path / "test" / "000001" / "depth" / f"{i:06d}.png")


@pytest.mark.parametrize("frame, depth_m, size, words", [
    (3, 0.8, (480, 640), "frame 3: the depth image is 640x480, but frame 1's is 320x240"),
    (3, 0.0008, (240, 320), "frame 3: its median depth is 0.001x frame 1's"),  # written in m, read as mm
    (2, 70.0, (240, 320), "frame 2: most of the depth image is saturated"),
])
def test_a_later_frames_depth_is_checked_before_the_first_runs_naming_it(tmp_path, frame, depth_m, size, words):
    _sequence(tmp_path, [1, 2, 3])
    _depth_of_frame(tmp_path, frame, depth_m, size)
    with pytest.raises(InputError, match=words) as err:
        sequence_frames(tmp_path, 1, None, None)
    assert err.value.path.endswith(f"depth/{frame:06d}.png")


def _world(tmp_path, t_of):
    poses = {str(i): {"R_w2c": rot_z(0.05 * i).ravel().tolist(), "t_w2c": t_of(i)} for i in (1, 2, 3, 4)}
    (tmp_path / "test" / "000001" / "scene_camera_world.json").write_text(json.dumps(poses))


@pytest.mark.parametrize("t_of, words", [
    (lambda i: [10_000.0 * i, 0.0, 900_000.0], "micrometres"),  # 1 cm steps written in um
    (lambda i: [0.01 * i, 0.0, 0.9], "metres"),  # 1 cm steps written in m
    (lambda i: [10.0 * i, 0.0, 900.0], None),  # mm, as BOP's
])
def test_world_translations_in_other_units_are_warned_about_once_naming_the_world_file(tmp_path, caplog, t_of,
                                                                                       words):
    _sequence(tmp_path, [1, 2, 3, 4])
    _world(tmp_path, t_of)
    with caplog.at_level("WARNING"):
        sequence_world(tmp_path, 1, None, "auto", [1, 2, 3, 4])
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    if words is None:
        assert warnings == []
    else:
        assert len(warnings) == 1 and "scene_camera_world.json" in warnings[0] and words in warnings[0], warnings


def test_an_object_keeps_its_world_pose_under_the_given_motion():
    T_w_obj = make_pose(rot_z(0.3), np.array([0.1, 0.2, 0.0]))
    T_c0_w = make_pose(rot_x(2.2), np.array([0.0, 0.1, 0.9]))
    T_c1_w = make_pose(rot_x(2.2) @ rot_z(0.05), np.array([0.02, 0.1, 0.91]))
    M = given_motion(T_c0_w, T_c1_w)
    assert np.allclose(M @ T_c0_w @ T_w_obj, T_c1_w @ T_w_obj)
    assert np.allclose(given_motion(T_c0_w, T_c0_w), np.eye(4)) and np.allclose(invert_pose(M) @ M, np.eye(4))


def test_an_object_is_lost_when_it_fits_much_worse_than_before():
    lost = lost_objects(np.array([0.9, 0.5, 0.3, 0.9]), np.array([0.1, 0.4, 0.0, 0.8]), floor=0.35, rise=0.2)
    assert lost.tolist() == [True, False, False, False]


@pytest.mark.parametrize("searched, found, words", [(0, 0, "tracked"), (2, 2, "2 objects re-found"),
                                                   (2, 1, "1 object re-found, 1 object still lost"),
                                                   (1, 0, "1 object still lost")])
def test_status_words(searched, found, words):
    assert status_words(searched, found) == words


def test_status_words_name_the_objects_recovered():
    assert status_words(1, 0, recovered=2) == "2 objects recovered, 1 object still lost"
