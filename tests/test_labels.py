"""Labelling helpers: snapping, fitting, residuals, errors, and the scene_gt.json files they write."""

import shutil

import numpy as np
import pytest

from workbench.errors import InputError
from workbench.evaluation import LocalEvaluator
from workbench.geometry import invert_pose, rot_z
from workbench.io import bop, readers
from workbench.label.frame import (
    fit_label,
    label_errors,
    labels_path,
    list_backups,
    load_labels,
    residual_map,
    restore_backup,
    save_labels,
    snap_to_plausible,
)
from workbench.physics import STATUS_REST
from workbench.problem.build import load_bop_problem
from workbench.score.metrics import position_error

pytestmark = pytest.mark.slow  # needs pybullet and OpenGL

# Labels go through JSON in mm with R re-orthonormalised on reading: float64 rounding, far below any use.
ROUNDTRIP_ATOL = 1e-12


@pytest.fixture(scope="module")
def scene(touching_dataset, tmp_path_factory):
    """A private copy of the frame (labels are written into it), its problem, the ground truth in the table frame,
    and a LocalEvaluator."""
    dataset = tmp_path_factory.mktemp("labels") / "dataset"
    shutil.copytree(touching_dataset, dataset)
    frame, problem = load_bop_problem(dataset, 0, 0)
    gt = invert_pose(problem.camera.T_cam_world)[None] @ frame.gt_T_cam_obj
    evaluator = LocalEvaluator(problem)
    yield dataset, frame, problem, gt, evaluator
    evaluator.close()


def _perturbed(gt):
    """Off the grid of fit_label's steps (1 cm, 4 degrees, halved), so a fit cannot land on the truth by chance."""
    T = gt.copy()
    T[0, :3, 3] += [0.013, -0.0085, 0.0]
    T[0, :3, :3] = rot_z(np.radians(7.0)) @ T[0, :3, :3]
    T[1, :3, 3] += [-0.0092, 0.011, 0.004]
    return T


def test_saved_labels_reload_identically_and_the_original_stays(scene):
    dataset, frame, problem, gt, _ = scene
    original = (dataset / "test" / "000000" / "scene_gt.json").read_bytes()
    path = save_labels(dataset, 0, 0, problem.camera.T_cam_world, [gt[0], None], frame.object_ids)
    assert path == labels_path(dataset, 0) and path.name == "scene_gt_labels.json"
    back = load_labels(dataset, 0, 0, problem.camera.T_cam_world, frame.object_ids)
    assert back[1] is None and np.allclose(back[0], gt[0], rtol=0, atol=ROUNDTRIP_ATOL)

    save_labels(dataset, 0, 0, problem.camera.T_cam_world, list(gt), frame.object_ids)  # replaces image 0's entry
    back = load_labels(dataset, 0, 0, problem.camera.T_cam_world, frame.object_ids)
    assert np.allclose(np.stack(back), gt, rtol=0, atol=ROUNDTRIP_ATOL)
    assert (dataset / "test" / "000000" / "scene_gt.json").read_bytes() == original
    assert load_labels(dataset, 0, 5, problem.camera.T_cam_world, frame.object_ids) == [None, None]


def test_original_ground_truth_is_replaced_only_when_asked_with_a_backup(scene, tmp_path):
    dataset, frame, problem, gt, _ = scene
    work = tmp_path / "dataset"
    shutil.copytree(dataset, work)
    scene_gt = work / "test" / "000000" / "scene_gt.json"
    original = scene_gt.read_bytes()
    moved = _perturbed(gt)
    with pytest.raises(InputError, match="original ground truth"):
        save_labels(work, 0, 0, problem.camera.T_cam_world, list(moved), frame.object_ids, path=scene_gt)
    assert scene_gt.read_bytes() == original and not list(scene_gt.parent.glob("*.bak-*"))

    save_labels(work, 0, 0, problem.camera.T_cam_world, list(moved), frame.object_ids, overwrite_original=True)
    backups = list(scene_gt.parent.glob("scene_gt.json.bak-*"))
    assert len(backups) == 1 and backups[0].read_bytes() == original
    reloaded = bop.load_frame(work, 0, 0)
    assert np.allclose(reloaded.gt_T_cam_obj, problem.camera.T_cam_world[None] @ moved, rtol=0, atol=ROUNDTRIP_ATOL)


def test_labelling_one_object_keeps_every_other_objects_truth(scene, tmp_path):
    """Overwriting scene_gt.json with one object labelled replaces that object's entry only: the frame keeps all
    its objects (it went from 4 to 1 on a real frame), and an entry of an object outside the problem stays too."""
    dataset, frame, problem, gt, _ = scene
    work = tmp_path / "dataset"
    shutil.copytree(dataset, work)
    scene_gt = work / "test" / "000000" / "scene_gt.json"
    content = readers.read_json(scene_gt)
    stranger = {"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 900], "obj_id": 99}
    content["0"].append(stranger)
    scene_gt.write_text(__import__("json").dumps(content))
    moved = _perturbed(gt)
    save_labels(work, 0, 0, problem.camera.T_cam_world, [None, moved[1]], frame.object_ids, overwrite_original=True)
    entries = readers.read_json(scene_gt)["0"]
    assert [e["obj_id"] for e in entries] == [*frame.object_ids, 99]
    assert entries[0] == content["0"][0] and entries[2] == stranger
    back = load_labels(work, 0, 0, problem.camera.T_cam_world, frame.object_ids, path=scene_gt)
    assert np.allclose(back[0], gt[0], rtol=0, atol=1e-6)
    assert np.allclose(back[1], moved[1], rtol=0, atol=ROUNDTRIP_ATOL)


def test_a_backup_is_restored_after_backing_up_the_current_truth(scene, tmp_path):
    """Two overwriting saves keep two backups, listed newest first; restoring the oldest puts the original bytes
    back, and the scene_gt.json it replaced is itself kept as a third backup."""
    dataset, frame, problem, gt, _ = scene
    work = tmp_path / "dataset"
    shutil.copytree(dataset, work)
    scene_gt = work / "test" / "000000" / "scene_gt.json"
    original = scene_gt.read_bytes()
    assert list_backups(work, 0) == []
    moved = _perturbed(gt)
    save_labels(work, 0, 0, problem.camera.T_cam_world, [moved[0], None], frame.object_ids, overwrite_original=True)
    once = scene_gt.read_bytes()
    save_labels(work, 0, 0, problem.camera.T_cam_world, [None, moved[1]], frame.object_ids, overwrite_original=True)
    twice = scene_gt.read_bytes()
    backups = list_backups(work, 0)
    assert [b.path.read_bytes() for b in backups] == [once, original]
    assert backups[0].time > backups[1].time

    path, kept = restore_backup(work, 0, backups[1].path.name)
    assert path == scene_gt and scene_gt.read_bytes() == original
    assert kept is not None and kept.read_bytes() == twice
    assert [b.path for b in list_backups(work, 0)] == [kept, *(b.path for b in backups)]
    assert np.allclose(bop.load_frame(work, 0, 0).gt_T_cam_obj, frame.gt_T_cam_obj, rtol=0, atol=1e-9)


@pytest.mark.parametrize("content, problem", [
    ('{"0": [{"obj_id": 1', "corrupt JSON"),
    ('[1, 2]', "must be a JSON object"),
    ('{"first": []}', "keys must be image ids"),
    ('{"0": {"obj_id": 1}}', "image 0: expected a list of objects"),
])
def test_a_damaged_backup_is_refused_naming_it_and_nothing_is_written(scene, tmp_path, content, problem):
    dataset, *_ = scene
    work = tmp_path / "dataset"
    shutil.copytree(dataset, work)
    folder = work / "test" / "000000"
    original = (folder / "scene_gt.json").read_bytes()
    damaged = folder / "scene_gt.json.bak-20240102T030405000006"
    damaged.write_text(content)
    assert [(b.path, b.time.isoformat()) for b in list_backups(work, 0)] == [(damaged, "2024-01-02T03:04:05.000006")]
    with pytest.raises(InputError, match=problem) as err:
        restore_backup(work, 0, damaged.name)
    assert err.value.path == str(damaged)
    assert (folder / "scene_gt.json").read_bytes() == original and list_backups(work, 0)[0].path == damaged
    assert len(list_backups(work, 0)) == 1
    for name in ("scene_gt.json", "../000000/scene_gt.json.bak-20240102T030405000006", "scene_gt.json.bak-missing"):
        with pytest.raises(InputError, match="not a backup"):
            restore_backup(work, 0, name)
    assert (folder / "scene_gt.json").read_bytes() == original


def test_snap_puts_a_floating_box_on_the_table(scene):
    _, _, problem, _, evaluator = scene
    floating = np.tile(np.eye(4), (2, 1, 1))
    floating[:, :3, 3] = [[-0.15, 0.0, 0.2], [0.15, 0.0, 0.2]]  # upright, 20 cm up, far apart
    snapped, moved, status = snap_to_plausible(problem, floating, evaluator)
    half_heights = [m.mesh.extents[2] / 2 for m in problem.models]
    assert status == STATUS_REST
    assert np.allclose(snapped[:, 2, 3], half_heights, atol=0.002)
    assert np.allclose(moved, 0.2 - np.array(half_heights), atol=0.005)


def test_fit_improves_a_perturbed_label(scene):
    _, _, problem, gt, evaluator = scene
    start = _perturbed(gt)
    fitted = fit_label(problem, start, evaluator)
    for k in range(problem.n_objects):
        before, after = position_error(gt[k], start[k]), position_error(gt[k], fitted[k])
        assert after < 0.3 * before and after < 0.003, (k, before, after)


def test_residual_map_and_errors(scene):
    _, frame, problem, gt, evaluator = scene
    good, bad = residual_map(problem, evaluator, gt), residual_map(problem, evaluator, _perturbed(gt))
    assert good.shape == bad.shape == problem.observed.shape
    assert good.sum() > bad.sum()

    rows = label_errors(problem, _perturbed(gt), [gt[0], None])
    assert [r["obj_id"] for r in rows] == frame.object_ids
    assert rows[0]["position_error_m"] == pytest.approx(np.hypot(0.013, 0.0085))
    assert rows[0]["rotation_error_deg"] == pytest.approx(7.0)
    assert rows[0]["add_s_m"] > 0
    assert rows[1] == {"obj_id": frame.object_ids[1], "position_error_m": None, "rotation_error_deg": None,
                       "add_s_m": None}
    assert label_errors(problem, gt, gt)[1]["add_s_m"] == 0.0
