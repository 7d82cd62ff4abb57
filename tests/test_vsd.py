"""BOP's Visible Surface Discrepancy: the pixel arithmetic on made-up distance images (no OpenGL), then rendered
objects (a mug whose handle the camera cannot see) and `workbench score` on the bundled demo frame."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from test_cli import _workbench

from workbench.cli import DEMO_DATASET
from workbench.geometry import make_pose, rot_z
from workbench.io import bop
from workbench.io.results import ResultRow, write_results_csv
from workbench.score.metrics import is_right, rotation_error
from workbench.score.vsd import VSDConfig, diameter, distance_image, frame_vsd, object_vsd, render_alone, vsd_errors

TAU, DELTA = VSDConfig().tau, VSDConfig().delta


def test_the_settings_are_bops():
    config = VSDConfig()
    assert (config.tau, config.theta, config.delta) == (0.020, 0.3, 0.015)  # metres: 20 mm, 15 mm
    grid = [0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5]
    assert list(config.ar_taus) == pytest.approx(grid) and list(config.ar_thetas) == pytest.approx(grid)


def _patch(value: float, rows=slice(10, 30), cols=slice(10, 30), shape=(40, 40)) -> np.ndarray:
    """A distance image (metres) holding ``value`` on a rectangle, 0 elsewhere."""
    out = np.zeros(shape)
    out[rows, cols] = value
    return out


def test_the_truth_has_no_discrepancy_and_an_object_30_cm_off_is_all_discrepancy():
    wall = np.full((40, 40), 1.5)
    gt = _patch(1.0)
    test = np.where(gt > 0, gt, wall)
    assert vsd_errors(test, gt, gt, [TAU], DELTA)[0] == 0.0
    # 30 cm further along the rays: the same pixels, each 30 cm from the truth (hidden, but where the truth is seen)
    assert vsd_errors(test, gt, gt + 0.3 * (gt > 0), [TAU], DELTA)[0] == 1.0
    # beside it (in front of the wall): no pixel shared
    assert vsd_errors(test, gt, _patch(1.0, cols=slice(32, 40)), [TAU], DELTA)[0] == 1.0


def test_only_what_the_camera_sees_counts():
    gt = _patch(1.0)
    test = np.full((40, 40), 1.5)
    test[10:30, 10:30] = 1.0
    test[20:30, 10:30] = 0.8  # an occluder in front of the object's lower half
    est = gt.copy()
    est[20:30, 10:30] = 1.05  # differs from the truth only behind the occluder
    est[30:35, 10:30] = 1.05  # and reaches further down, still behind it
    test[30:35, 10:30] = 0.8
    assert vsd_errors(test, gt, est, [TAU], DELTA)[0] == 0.0
    # The same difference in plain view: half the union
    test[20:35, 10:30] = 1.5
    assert vsd_errors(test, gt, est, [TAU], DELTA)[0] == pytest.approx(300 / 500)


def test_pixels_without_depth_count_as_visible_and_nothing_visible_is_an_error_of_one():
    gt = _patch(1.0)
    est = _patch(1.0, cols=slice(20, 40))  # half of it over the truth
    none = np.zeros((40, 40))  # the sensor saw nothing (a shiny object): BOP 2019 counts every rendered pixel
    assert vsd_errors(none, gt, est, [TAU], DELTA)[0] == pytest.approx(400 / 600)
    assert vsd_errors(none, np.zeros((40, 40)), np.zeros((40, 40)), [TAU, 0.05], DELTA).tolist() == [1.0, 1.0]


def test_the_step_cost_and_the_average_recall_grid():
    gt = _patch(1.0)
    test = gt.copy()
    off = 2.0 ** -7  # 7.8 mm behind (a binary fraction: exact): seen (within delta 15 mm), off at every pixel
    est = gt + off * (gt > 0)
    assert vsd_errors(test, gt, est, [off, off + 1e-6], DELTA).tolist() == [1.0, 0.0]  # an error when >= tau
    scored = object_vsd(test, gt, est, diameter=0.1)
    # tau 5 mm (0.05 of the diameter) calls every pixel wrong, for every theta; the other 9 tolerances none
    assert scored.error == 0.0 and scored.right and scored.ar == pytest.approx(0.9)
    # theta: an error must be below it. 30 % of the pixels wrong is not right at theta 0.3
    est[10:16, 10:30] = 1.5
    test[10:16, 10:30] = 1.5
    assert object_vsd(test, gt, est, diameter=0.1).error == pytest.approx(0.3)
    assert not object_vsd(test, gt, est, diameter=0.1).right


def test_distance_along_the_ray_and_the_diameter():
    K = np.array([[100.0, 0.0, 2.0], [0.0, 100.0, 1.0], [0.0, 0.0, 1.0]])
    depth = np.zeros((3, 103))
    depth[1, 2] = depth[1, 102] = 2.0
    d = distance_image(depth, K)
    assert d[1, 2] == 2.0 and d[1, 102] == pytest.approx(2.0 * np.sqrt(2.0)) and d[0, 0] == 0.0
    assert diameter(trimesh.creation.box([0.03, 0.04, 0.12])) == pytest.approx(0.13)


# ---------------------------------------------------------------------------------------------------------------
# Rendered: the renderer's depth at the frame's full resolution

K = np.array([[400.0, 0.0, 159.5], [0.0, 400.0, 119.5], [0.0, 0.0, 1.0]])
W, H = 320, 240
R_MUG, HANDLE = 0.04, 0.015  # body radius, how far the handle sticks out (metres)


def _mug() -> trimesh.Trimesh:
    """A cylinder about its z axis (origin at its centre) with a box handle along +x: no symmetry at all."""
    body = trimesh.creation.cylinder(radius=R_MUG, height=0.1, sections=64)
    handle = trimesh.creation.box([HANDLE + 0.005, 0.01, 0.05])
    handle.apply_translation([R_MUG + HANDLE / 2 - 0.0025, 0.0, 0.0])
    return trimesh.util.concatenate([body, handle])


# Upright in the image (mug z = camera -y), the handle pointing straight away from the camera (mug x = camera z)
MUG_GT = make_pose(np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]), [0.0, 0.0, 0.8])


@pytest.fixture(scope="module")
def mug_frame():
    """The mug's mesh and an observed depth image (H, W) metres: the mug at MUG_GT before a wall 1.2 m away."""
    mesh = _mug()
    [alone] = render_alone(K, W, H, [mesh], [(0, MUG_GT)])
    return mesh, np.where(alone > 0, alone, 1.2).astype(np.float32)


@pytest.mark.slow  # OpenGL
def test_a_hidden_handle_is_no_error_but_a_misplaced_mug_is(mug_frame):
    mesh, depth = mug_frame

    def vsd(T_est):
        return frame_vsd(depth, K, [mesh], [diameter(mesh)], [(0, MUG_GT, T_est)])[0]

    truth = vsd(MUG_GT)
    assert truth.error < 0.01 and truth.right and truth.ar == 1.0
    for offset in ([0.3, 0.0, 0.0], [0.0, 0.0, 0.3]):  # 30 cm to the side, 30 cm further away
        away = MUG_GT.copy()
        away[:3, 3] += offset
        assert vsd(away).error == 1.0 and not vsd(away).right and vsd(away).ar == 0.0

    # Turned 30 degrees about its axis: the handle stays behind the body, the body looks the same
    hidden = MUG_GT @ make_pose(rot_z(np.radians(30.0)), np.zeros(3))
    assert rotation_error(MUG_GT, hidden) == pytest.approx(30.0) and not is_right(MUG_GT, hidden)
    assert vsd(hidden).error < 0.01 and vsd(hidden).right
    # Turned 90 degrees: the handle sticks out beside the body, pixels the truth does not have
    shown = MUG_GT @ make_pose(rot_z(np.radians(90.0)), np.zeros(3))
    assert vsd(shown).error > 0.05


@pytest.mark.slow  # OpenGL
def test_an_object_without_an_estimate_is_an_error_of_one(mug_frame):
    mesh, depth = mug_frame
    [missed] = frame_vsd(depth, K, [mesh], [diameter(mesh)], [(0, MUG_GT, None)])
    assert (missed.error, missed.right, missed.ar) == (1.0, False, 0.0)


@pytest.mark.slow  # a `workbench score` process: OpenGL
def test_score_reports_vsd_per_object_and_in_the_summary(tmp_path):
    frame = bop.load_frame(DEMO_DATASET, 0, 0)
    truth = [ResultRow(0, 0, obj_id, 1.0, T.copy(), 1.0) for obj_id, T in zip(frame.object_ids, frame.gt_T_cam_obj)]
    results = tmp_path / "truth.csv"
    write_results_csv(results, truth)
    run = _workbench("score", DEMO_DATASET, results, "--json", tmp_path / "truth.json")
    assert run.returncode == 0, run.stderr
    n = len(truth)
    assert f"{n}/{n} objects right (within 2 cm" in run.stdout  # the existing line, as before
    assert f"{n}/{n} objects right by BOP's visible surface discrepancy" in run.stdout and "AR_VSD 1.000" in run.stdout
    scores = json.loads((tmp_path / "truth.json").read_text())
    assert [o["vsd"] for o in scores["objects"]] == [0.0] * n
    assert all(o["vsd_right"] and o["ar_vsd"] == 1.0 and o["right"] for o in scores["objects"])
    assert scores["summary"]["vsd_right"] == n and scores["summary"]["ar_vsd"] == 1.0
    # BOP 2019's AR: the truth recalls every threshold of the three
    assert all(o["mssd_mm"] == pytest.approx(0.0, abs=1e-9) and o["mspd_px"] == pytest.approx(0.0, abs=1e-6)
               for o in scores["objects"])
    assert [scores["summary"][k] for k in ("ar", "ar_mssd", "ar_mspd")] == [1.0, 1.0, 1.0]
    assert "AR 1.000 = mean of AR_VSD 1.000, AR_MSSD 1.000 and AR_MSPD 1.000" in run.stdout
    assert scores["summary"]["vsd_tau_mm"] == pytest.approx(20.0) and scores["summary"]["vsd_theta"] == 0.3

    # The first object 30 cm away; the second not estimated at all
    away = truth[0].T_cam_obj.copy()
    away[:3, 3] += [0.3, 0.0, 0.0]
    write_results_csv(results, [ResultRow(0, 0, truth[0].obj_id, 1.0, away, 1.0)])
    run = _workbench("score", DEMO_DATASET, results, "--json", tmp_path / "truth.json")  # ours: replaced
    assert run.returncode == 0, run.stderr
    scores = json.loads((tmp_path / "truth.json").read_text())
    first, second = scores["objects"][:2]
    assert first["vsd"] == 1.0 and not first["vsd_right"] and first["ar_vsd"] == 0.0
    assert second["position_cm"] is None and second["vsd"] == 1.0 and second["ar_vsd"] == 0.0
    # 30 cm is beyond every MSSD threshold (at most half a diameter) and every MSPD one (at most 50 px)
    assert first["mssd_mm"] == pytest.approx(300.0, rel=1e-6) and first["ar_mssd"] == 0.0 and first["ar_mspd"] == 0.0
    assert second["mssd_mm"] is None and second["ar_mssd"] == 0.0 and second["ar_mspd"] == 0.0
    rest = scores["objects"][2:]
    assert scores["summary"]["ar"] == pytest.approx(np.mean([(o["ar_vsd"] + o["ar_mssd"] + o["ar_mspd"]) / 3
                                                             for o in [first, second, *rest]]))
    assert scores["summary"]["vsd_right"] == n - 2 and f"{n - 2}/{n} objects right by BOP's" in run.stdout
