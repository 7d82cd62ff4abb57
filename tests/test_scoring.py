"""`workbench score`: a results CSV against the dataset's ground truth."""

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
from test_cli import _workbench

from workbench.errors import InputError
from workbench.geometry import make_pose, rot_z
from workbench.io import bop
from workbench.io.results import ResultRow, write_results_csv
from workbench.score.scoring import instance_groups, match, report, score_results, summary

pytestmark = pytest.mark.slow  # needs generated scenes (pybullet)


def _truth_rows(dataset):
    frame = bop.load_frame(dataset, 0, 0)
    return frame, [ResultRow(0, 0, obj_id, 1.0, T.copy(), 1.0)
                   for obj_id, T in zip(frame.object_ids, frame.gt_T_cam_obj)]


def test_the_truth_scores_right_and_a_moved_object_does_not(touching_dataset):
    frame, rows = _truth_rows(touching_dataset)
    [scored] = score_results(touching_dataset, rows)
    assert scored.right and len(scored.objects) == len(frame.object_ids)
    assert all(o.position_cm < 1e-6 and o.rotation_deg < 1e-3 and o.add_s_mm < 1e-6 for o in scored.objects)

    rows[0].T_cam_obj[:3, 3] += [0.03, 0.0, 0.0]  # 3 cm off
    # the other box turned half about its own z axis: the same box, a declared symmetry of the dataset
    rows[1].T_cam_obj = rows[1].T_cam_obj @ make_pose(rot_z(np.pi), np.zeros(3))
    [scored] = score_results(touching_dataset, rows)
    assert not scored.right
    assert not scored.objects[0].right and abs(scored.objects[0].position_cm - 3.0) < 1e-6
    assert scored.objects[1].right and scored.objects[1].rotation_deg < 1e-3


def test_a_missing_estimate_is_wrong_and_an_extra_row_is_counted(touching_dataset):
    frame, rows = _truth_rows(touching_dataset)
    stranger = ResultRow(0, 0, 99, 0.5, rows[0].T_cam_obj.copy(), 1.0)  # an object the frame does not hold
    [scored] = score_results(touching_dataset, [rows[0], stranger])
    assert scored.unmatched_rows == 1
    assert scored.objects[0].right and not scored.objects[1].estimated and not scored.objects[1].right


def test_only_each_objects_top_row_is_its_estimate_the_others_are_modes(touching_dataset):
    frame, rows = _truth_rows(touching_dataset)
    away = rows[0].T_cam_obj.copy()
    away[:3, 3] += [0.1, 0.0, 0.0]
    truth = replace(rows[0], score=0.8)  # the object's modes: probabilities that sum to 1
    mode = ResultRow(0, 0, frame.object_ids[0], 0.2, away, 1.0)  # a less likely mode 10 cm off: not matched
    [scored] = score_results(touching_dataset, [mode, truth, *rows[1:]])
    assert scored.unmatched_rows == 0 and scored.objects[0].right
    top = ResultRow(0, 0, frame.object_ids[0], 0.8, away, 1.0)  # more likely than the truth's row: the estimate
    [scored] = score_results(touching_dataset, [top, replace(rows[0], score=0.2), *rows[1:]])
    assert not scored.objects[0].right and scored.objects[1].right


def test_modes_that_are_no_probabilities_are_refused_naming_the_frame_and_object(touching_dataset):
    frame, rows = _truth_rows(touching_dataset)  # each scored 1.0
    second = replace(rows[0], score=0.8)
    with pytest.raises(InputError, match=f"object {frame.object_ids[0]}: 2 rows for 1 instance.*sum to 1.8"):
        score_results(touching_dataset, [second, *rows])


def test_instances_of_one_object_are_matched_nearest_first():
    gt = np.repeat(np.eye(4)[None], 3, axis=0)
    gt[:, 0, 3] = [0.0, 0.1, 0.2]
    gt[2] = np.nan  # an instance without ground truth is never matched
    est = gt[[1, 0]].copy()
    est[:, 0, 3] = [0.11, 0.01]
    assert sorted(match(gt, est, np.eye(4)[None])) == [(0, 1), (1, 0)]


def test_each_instance_of_an_object_is_its_own_run_of_modes():
    def row(score, x):
        return ResultRow(0, 0, 5, score, make_pose(np.eye(3), [x, 0.0, 1.0]), 1.0)

    # Two instances, as `estimate` writes them: the first's second mode outscores the second's estimate.
    a, a2, b, b2, b3 = row(0.52, 0.0), row(0.48, 0.05), row(0.45, 0.3), row(0.3, 0.35), row(0.25, 0.4)
    assert instance_groups([a, a2, b, b2, b3], 2) == [[a, a2], [b, b2, b3]]
    # Another tool's rows, one per instance and any score: the best ones, each its own.
    c, d, e = row(0.9, 0.0), row(0.3, 0.3), row(0.8, 0.6)
    assert instance_groups([c, d, e], 2) == [[c], [e]]
    f, g = row(1.0, 0.0), row(1.0, 0.3)  # one row each, probability 1 (one mode)
    assert instance_groups([f, g], 2) == [[f], [g]]


def test_score_command_prints_the_summary_and_names_a_foreign_frame(touching_dataset, tmp_path):
    _, rows = _truth_rows(touching_dataset)
    good = tmp_path / "good.csv"
    write_results_csv(good, rows)
    run = _workbench("score", touching_dataset, good, "--json", tmp_path / "scores.json")
    assert run.returncode == 0, run.stderr
    assert f"{len(rows)}/{len(rows)} objects right" in run.stdout and "1 with every object right" in run.stdout
    assert (tmp_path / "scores.json").is_file()

    foreign = tmp_path / "foreign.csv"
    write_results_csv(foreign, [ResultRow(7, 3, r.obj_id, r.score, r.T_cam_obj, r.time) for r in rows])
    run = _workbench("score", touching_dataset, foreign)
    assert run.returncode == 2 and "foreign.csv" in run.stderr and "scene 7 image 3" in run.stderr
    assert "Traceback" not in run.stderr


def test_hidden_objects_and_categories_are_counted_apart(touching_dataset, tmp_path):
    """An object under 10 % visible (scene_gt_info.json) is counted apart from BOP's targets, and a generated set's
    objects per category (scenes.json); every object still counts in the headline."""
    dataset = tmp_path / "set"
    shutil.copytree(touching_dataset, dataset)
    info_path = dataset / "test" / "000000" / "scene_gt_info.json"
    info = json.loads(info_path.read_text())
    info["0"][1]["visib_fract"] = 0.05
    info_path.write_text(json.dumps(info))
    _, rows = _truth_rows(dataset)
    rows[1].T_cam_obj[:3, 3] += [0.05, 0.0, 0.0]  # the hidden one 5 cm off
    frames = score_results(dataset, rows)
    assert [o.hidden for o in frames[0].objects] == [False, True] and frames[0].category == "touching"
    totals = summary(frames)
    assert (totals["objects"], totals["objects_right"]) == (2, 1)
    assert totals["visible"] == {"objects": 1, "objects_right": 1}
    assert totals["hidden"] == {"objects": 1, "objects_right": 0}
    assert totals["categories"]["touching"]["hidden"] == {"objects": 1, "objects_right": 0}
    text = "\n".join(report(frames))
    assert "1/2 objects right" in text and "(BOP's test targets): 1/1; of the 1 hidden ones" in text
    assert "per category, right/objects (objects under 10% visible apart): touching 1/1 + hidden 0/1" in text

    info_path.unlink()  # a dataset that does not say: no object is hidden
    (dataset / "scenes.json").unlink()
    frames = score_results(dataset, rows)
    assert not any(o.hidden for o in frames[0].objects) and frames[0].category is None
    assert "visible" not in summary(frames) and "categories" not in summary(frames)
