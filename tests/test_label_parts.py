"""The parts of sequence labelling on constructed arrays: a label's check against the depth, the labels carried
through a sequence (moves, an end), the BOP entries merged beside what a file held, the files' names and refusals,
and the spread of frames the multi-view fit sums. No rendering or physics: quick."""

import json

import numpy as np
import pytest

from workbench.errors import InputError
from workbench.label.check import CheckConfig, check_objects, object_shares, seen_masks, worst
from workbench.label.multiview import spread
from workbench.label.run import LabelRun, gone_from
from workbench.label.sequence import (
    ObjectLabel,
    SequenceLabels,
    gt_entries,
    gt_info_entry,
    label_files,
    merged_frame,
    write_sequence,
)


def _plane(depth, shape=(20, 20)):
    return np.full(shape, depth, dtype=np.float32)


def test_a_label_on_its_surface_agrees_and_one_off_it_is_flagged():
    observed = _plane(1.0)
    on = _plane(1.003)[None]  # 3 mm: within the sensor's noise
    behind = _plane(1.05)[None]  # 5 cm behind the surface the camera sees
    floating = _plane(0.95)[None]  # 5 cm in front: the camera sees past it
    [good], [far], [near] = (check_objects([7], a, observed) for a in (on, behind, floating))
    assert (good.agree, good.flagged, good.reason) == (1.0, False, "")
    assert far.flagged and far.front == 1.0 and "in front of it" in far.reason
    assert near.flagged and near.through == 1.0 and "sees past it" in near.reason


def test_only_where_a_label_is_nearest_and_the_sensor_read_counts():
    observed = _plane(1.0)
    observed[:, :5] = 0  # no reading on the left quarter
    front = np.zeros((20, 20), np.float32)
    front[:, :10] = 0.9  # object 0 covers the left half, nearer
    back = _plane(1.0)  # object 1 everywhere, behind object 0 on the left half
    seen = seen_masks(np.stack([front, back]), observed)
    assert seen[0].sum() == 5 * 20 and seen[1].sum() == 10 * 20
    shares = object_shares(np.stack([front, back]), observed, CheckConfig())
    assert shares[1].tolist() == [200, 1.0, 0.0, 0.0]  # object 1 agrees where it is seen; hidden pixels not counted
    assert shares[0][2] == 1.0  # object 0 floats 10 cm in front of what is seen


def test_an_object_seen_on_too_few_pixels_is_not_checked_nor_flagged():
    alone = np.zeros((1, 20, 20), np.float32)
    alone[0, :2, :2] = 2.0  # 4 pixels, far behind the table
    [c] = check_objects([3], alone, _plane(1.0), CheckConfig(min_pixels=30))
    assert (c.checked, c.flagged) == (False, False)
    assert worst([c]) is None


def test_check_config_refuses_impossible_tolerances():
    for bad in (CheckConfig(agree_m=0.03, tau_m=0.02), CheckConfig(min_agree=1.5), CheckConfig(min_pixels=0)):
        with pytest.raises(InputError):
            bad.validate()


def _labels():
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.0, 0.05]
    cams = {i: np.eye(4) for i in range(5)}
    for i in cams:
        cams[i][2, 3] = 1.0 + 0.01 * i  # the camera backs away 1 cm a frame
    return SequenceLabels(4, cams, [ObjectLabel(1, T.copy()), ObjectLabel(2, T.copy())])


def test_labels_are_carried_by_the_camera_and_moves_and_ends_hold_from_their_frame():
    labels = _labels()
    moved = np.eye(4)
    moved[:3, 3] = [0.2, 0.0, 0.05]
    labels.moved_to(0, 2, moved)
    labels.ends_at(1, 3)
    assert np.allclose(labels.camera_poses(1)[0][:3, 3], [0.1, 0.0, 1.06])
    assert np.allclose(labels.camera_poses(2)[0][:3, 3], [0.2, 0.0, 1.07])  # moved from frame 2 on
    assert labels.camera_poses(4)[1] is None and labels.camera_poses(3)[1] is not None  # ended after frame 3
    _, present = labels.world_poses(4)
    assert present.tolist() == [True, False]
    entry = gt_entries(labels, 0)[0]
    assert entry["obj_id"] == 1 and np.allclose(entry["cam_t_m2c"], [100.0, 0.0, 1050.0])  # millimetres


def test_a_merged_frame_keeps_other_objects_entries_and_their_info_aligned():
    old_gt = [{"obj_id": 9, "cam_R_m2c": [1] * 9, "cam_t_m2c": [0, 0, 1]}, {"obj_id": 1, "old": True}]
    old_info = [{"visib_fract": 0.9}, {"visib_fract": 0.1}]
    gt, info = merged_frame(old_gt, old_info, [1, 2], [{"obj_id": 1, "new": True}, {"obj_id": 2, "new": True}],
                            [{"visib_fract": 0.5}, {"visib_fract": 0.7}])
    assert [e["obj_id"] for e in gt] == [9, 1, 2] and gt[0] == old_gt[0] and gt[1]["new"]
    assert [i["visib_fract"] for i in info] == [0.9, 0.5, 0.7]


def test_gt_info_counts_what_is_visible_and_boxes_it():
    alone = np.zeros((10, 10), np.float32)
    alone[2:6, 3:8] = 1.0  # 20 pixels drawn
    observed = _plane(1.0, (10, 10))
    observed[2:4, 3:8] = 0.5  # the top half hidden behind something nearer
    info = gt_info_entry(alone, observed)
    assert (info["px_count_all"], info["px_count_visib"], info["visib_fract"]) == (20, 10, 0.5)
    assert info["bbox_obj"] == [3, 2, 5, 4] and info["bbox_visib"] == [3, 4, 5, 2]


def _scene(root):
    """A dataset folder holding scene 4 (only what naming its files needs)."""
    scene = root / "test" / "000004"
    scene.mkdir(parents=True)
    (scene / "scene_camera.json").write_text("{}")
    return scene


def test_label_files_never_name_the_datasets_own_files_without_overwrite(tmp_path):
    scene = _scene(tmp_path)
    files = label_files(tmp_path, 4)
    assert (files.labels.name, files.info.name) == ("scene_gt_labels.json", "scene_gt_info_labels.json")
    mine = label_files(tmp_path, 4, path=tmp_path / "mine.json")
    assert (mine.info.name, mine.provenance.name) == ("mine_info.json", "mine_provenance.json")
    for bad in (scene / "scene_gt.json", tmp_path / "scene_gt_info.json"):
        with pytest.raises(InputError, match="original ground truth"):
            label_files(tmp_path, 4, path=bad)
    assert label_files(tmp_path, 4, overwrite_original=True).labels == scene / "scene_gt.json"


def test_written_labels_merge_into_the_file_and_say_where_they_came_from(tmp_path):
    labels = _labels()
    labels.checked.add(0)
    _scene(tmp_path)
    path = tmp_path / "labels.json"
    path.write_text(json.dumps({"0": [{"obj_id": 5, "cam_R_m2c": [1] * 9, "cam_t_m2c": [0, 0, 1]}], "99": []}))
    files = label_files(tmp_path, 4, path=path)
    infos = {i: [gt_info_entry(np.ones((2, 2)), np.ones((2, 2)))] * 2 for i in labels.frames}
    write_sequence(files, labels, infos, {})
    gt = json.loads(path.read_text())
    assert sorted(gt, key=int) == ["0", "1", "2", "3", "4", "99"] and [e["obj_id"] for e in gt["0"]] == [5, 1, 2]
    info = json.loads(files.info.read_text())
    assert len(info["0"]) == 3 and info["0"][0]["visib_fract"] == 0.0  # the kept entry: nothing known of it
    prov = json.loads(files.provenance.read_text())
    assert prov["frames"]["0"]["source"] == "checked" and prov["frames"]["1"]["source"] == "propagated"


def test_a_file_that_cannot_be_merged_into_is_refused_and_left_as_it_was(tmp_path):
    _scene(tmp_path)
    path = tmp_path / "labels.json"
    path.write_text(json.dumps({"0": {"not": "a list"}}))
    with pytest.raises(InputError, match="expected a list"):
        write_sequence(label_files(tmp_path, 4, path=path), _labels(), {}, {})
    assert json.loads(path.read_text()) == {"0": {"not": "a list"}}
    assert not (tmp_path / "labels_provenance.json").exists()


def test_an_object_seen_through_to_the_end_is_said_to_be_gone_from_there():
    labels = _labels()
    see_through = check_objects([1, 2], np.stack([_plane(1.0), _plane(0.9)]), _plane(1.0))
    fine = check_objects([1, 2], np.stack([_plane(1.0), _plane(1.0)]), _plane(1.0))
    checks = {i: fine if i < 3 else see_through for i in labels.frames}
    run = LabelRun(labels, checks, {}, {}, {})
    assert run.flagged == [3, 4] and gone_from(run) == {2: 3}


def test_the_fit_spreads_over_the_sequence_with_both_ends():
    assert spread(list(range(1, 21)), 4) == [1, 7, 14, 20]
    assert spread([3, 4], 6) == [3, 4]


def test_sequence_labels_keep_their_poses_moves_and_checks_through_json():
    """``labels_json`` and ``parse_labels`` (a session keeps the labels this way): the same labels back; a pose
    that is no rigid transform, or a frame key that is no image id, is refused naming its entry."""
    from workbench.geometry import make_pose, rot_z
    from workbench.label.sequence import ObjectLabel, SequenceLabels, labels_json, parse_labels

    T = make_pose(rot_z(0.3), np.array([0.1, -0.2, 0.05]))
    labels = SequenceLabels(3, {1: np.eye(4), 2: T}, [ObjectLabel(5, T, None, 2, {2: np.eye(4)}),
                                                      ObjectLabel(7, np.eye(4), 1)], {2})
    back = parse_labels(json.loads(json.dumps(labels_json(labels))))
    assert back.scene_id == 3 and back.frames == [1, 2] and back.checked == {2} and back.obj_ids == [5, 7]
    assert np.array_equal(back.objects[0].T_world_obj, T) and np.array_equal(back.objects[0].moves[2], np.eye(4))
    assert (back.objects[0].first, back.objects[0].last, back.objects[1].first) == (None, 2, 1)
    bad = labels_json(labels)
    bad["objects"][1]["moves"] = {"x": np.eye(4).ravel().tolist()}
    with pytest.raises(ValueError, match=r"objects\[1\]\.moves"):
        parse_labels(bad)
    bad = labels_json(labels)
    bad["cameras"]["2"] = (2 * np.eye(4)).ravel().tolist()
    with pytest.raises(ValueError, match=r"cameras\[2\]"):
        parse_labels(bad)
