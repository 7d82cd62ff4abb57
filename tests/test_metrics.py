"""Pose metrics on hand-made cases."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from workbench.geometry import make_pose, pose_from_xyz_rpy, rot_x, rot_y, rot_z
from workbench.score import metrics

CRACKER = (0.16, 0.06, 0.21)


def _box_vertices(extents) -> np.ndarray:
    e = np.asarray(extents) / 2
    return np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * e


def test_box_symmetries_count_and_map_the_box_onto_itself():
    for extents, n in ((CRACKER, 4), ((0.085, 0.085, 0.2), 8), ((0.1, 0.1, 0.1), 24)):
        S = metrics.box_symmetries(extents)
        assert S.shape == (n, 4, 4) and np.allclose(S[0], np.eye(4))
        v = _box_vertices(extents)
        for T in S:
            assert np.isclose(np.linalg.det(T[:3, :3]), 1)
            moved = v @ T[:3, :3].T
            assert all(np.min(np.linalg.norm(v - p, axis=1)) < 1e-12 for p in moved)


def test_a_box_turned_180_degrees_has_no_symmetric_error():
    S = metrics.box_symmetries(CRACKER)
    T_gt = pose_from_xyz_rpy([0.1, -0.05, 0.03, 0.2, -0.1, 1.0])
    T_est = T_gt @ make_pose(rot_z(np.pi), np.zeros(3))  # a half turn about the box's own z axis
    assert metrics.rotation_error(T_gt, T_est) == pytest.approx(180.0)
    assert metrics.rotation_error(T_gt, T_est, S) == pytest.approx(0.0, abs=1e-5)
    assert np.allclose(metrics.rpy_errors(T_gt, T_est, S), 0, atol=1e-5)
    assert np.max(metrics.rpy_errors(T_gt, T_est)) > 90
    v = _box_vertices(CRACKER)
    assert metrics.mssd(T_gt, T_est, v, S) == pytest.approx(0.0, abs=1e-9)
    assert metrics.mssd(T_gt, T_est, v) == pytest.approx(np.hypot(0.16, 0.06))  # diagonally opposite corners
    assert metrics.add_s(T_gt, T_est, v) == pytest.approx(0.0, abs=1e-9)
    assert metrics.position_error(T_gt, T_est) == 0.0


def test_a_symmetry_of_a_model_whose_origin_is_off_its_centre_moves_the_origin_and_costs_nothing():
    """YCB-Video's wood block: its origin lies at one end, 3.5 cm from the centre along z, so the block upside
    down (the symmetry turns it and shifts it back by 3.5 cm) is the same block with its origin 3.5 cm away."""
    flip = make_pose(rot_x(np.pi), [0.0, 0.0, 0.035])
    S = np.stack([np.eye(4), flip])
    T_gt = pose_from_xyz_rpy([0.1, -0.05, 0.03, 0.2, -0.1, 1.0])
    T_est = T_gt @ flip
    assert metrics.position_error(T_gt, T_est) == pytest.approx(0.035)
    assert metrics.position_error(T_gt, T_est, S) == pytest.approx(0.0, abs=1e-12)
    assert metrics.rotation_error(T_gt, T_est, S) == pytest.approx(0.0, abs=1e-5)
    shifted = T_est.copy()
    shifted[:3, 3] += [0.01, 0.0, 0.0]
    assert metrics.position_error(T_gt, shifted, S) == pytest.approx(0.01)


def test_a_quarter_turn_is_not_a_symmetry_of_a_cracker_box():
    S = metrics.box_symmetries(CRACKER)
    T_gt = np.eye(4)
    T_est = make_pose(rot_z(np.pi / 2), np.zeros(3))
    assert metrics.rotation_error(T_gt, T_est, S) == pytest.approx(90.0)
    assert metrics.rpy_errors(T_gt, T_est, S) == pytest.approx([0, 0, 90])


def test_rpy_errors_are_about_the_table_axes_even_for_a_box_on_its_side():
    # Lying on its side the box has pitch 90 degrees, where differencing Euler angles is meaningless.
    T_gt = make_pose(rot_y(np.pi / 2), [0, 0, 0.08])
    T_est = make_pose(rot_x(np.radians(5)) @ rot_y(np.pi / 2), [0.03, 0.04, 0.08])
    assert metrics.rpy_errors(T_gt, T_est, metrics.box_symmetries(CRACKER)) == pytest.approx([5, 0, 0], abs=1e-6)
    assert metrics.position_error(T_gt, T_est) == pytest.approx(0.05)
    T_yaw = make_pose(rot_z(np.radians(-12)) @ rot_y(np.pi / 2), [0, 0, 0.08])
    assert metrics.rpy_errors(T_gt, T_yaw) == pytest.approx([0, 0, 12], abs=1e-6)
    assert metrics.rotation_error(T_gt, T_yaw) == pytest.approx(12)


def test_translation_errors_in_add_s_and_mssd():
    pts = metrics.model_points(trimesh.creation.box(extents=CRACKER), n=500)
    T_est = make_pose(np.eye(3), [0.0, 0.0, 0.01])
    assert metrics.mssd(np.eye(4), T_est, pts) == pytest.approx(0.01)
    # ADD-S: points on the top and bottom faces move 1 cm off the surface, side points slide along it.
    assert 0.0 < metrics.add_s(np.eye(4), T_est, pts) < 0.01


def _history(steps: list[tuple[float, float]]) -> np.ndarray:
    """(T, 2, 4, 4): object 0 moves by (metres, degrees about z) per step, object 1 stays put."""
    poses, T = [], np.eye(4)
    poses.append(T)
    for dx, deg in steps:
        T = make_pose(rot_z(np.radians(deg)) @ T[:3, :3], T[:3, 3] + [dx, 0, 0])
        poses.append(T)
    H = np.stack(poses)
    return np.stack([H, np.broadcast_to(np.eye(4), H.shape)], axis=1)


def test_iterations_to_converge():
    assert metrics.iterations_to_converge(_history([(0.05, 0)] * 3 + [(0.001, 0.5)] * 4)) == 3
    assert metrics.iterations_to_converge(_history([(0.001, 0)] * 5)) == 0
    assert metrics.iterations_to_converge(_history([(0.001, 0)] * 4 + [(0.0, 10.0)])) == 6  # T: still turning
    # A jump back after settling restarts the count; a 180-degree flip only counts without symmetries.
    assert metrics.iterations_to_converge(_history([(0.05, 0), (0.0, 0), (0.02, 0), (0.0, 0), (0.0, 0)])) == 3
    flip = _history([(0.0, 0), (0.0, 180.0), (0.0, 0), (0.0, 0)])
    S = [metrics.box_symmetries(CRACKER)] * 2
    assert metrics.iterations_to_converge(flip) == 2
    assert metrics.iterations_to_converge(flip, symmetries=S) == 0


def test_is_right_within_two_cm_and_ten_degrees_up_to_symmetry():
    T = make_pose(rot_z(0.3), np.array([0.1, 0.2, 0.05]))
    assert metrics.is_right(T, T)
    shifted = T.copy()
    shifted[0, 3] += 0.99 * metrics.RIGHT_CM / 100
    assert metrics.is_right(T, shifted)
    shifted[0, 3] += 0.02 * metrics.RIGHT_CM / 100
    assert not metrics.is_right(T, shifted)
    assert metrics.is_right(T, T @ make_pose(rot_z(np.radians(0.99 * metrics.RIGHT_DEG)), np.zeros(3)))
    half = T @ make_pose(rot_z(np.pi), np.zeros(3))
    assert not metrics.is_right(T, half)
    assert metrics.is_right(T, half, np.stack([np.eye(4), make_pose(rot_z(np.pi), np.zeros(3))]))


def test_heading_offset_is_the_signed_turn_about_the_vertical_from_the_estimate_to_the_truth():
    vertical = np.array([0.0, 0.6, 0.8])  # a camera frame's view of the table's z
    # An object lying on its side in the table frame (its z axis horizontal), then seen from the camera.
    R_table = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]) @ np.array(
        [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    frame_R = np.column_stack([[1.0, 0.0, 0.0], np.cross(vertical, [1.0, 0.0, 0.0]), vertical])  # table -> camera
    est = make_pose(frame_R @ R_table, [0.1, 0.0, 0.7])
    for turn in (-170.0, -35.0, 0.0, 60.0, 179.0):
        about = frame_R @ rot_z(np.radians(turn)) @ frame_R.T
        truth = make_pose(about @ est[:3, :3], [0.1, 0.0, 0.7])
        assert metrics.heading_offset_deg(truth, est, vertical) == pytest.approx(turn, abs=1e-6)
    # A symmetry of the model (its half turn about its own z) is no turn at all.
    half = make_pose(rot_z(np.pi), np.zeros(3))
    truth = make_pose(frame_R @ rot_z(np.radians(20.0)) @ frame_R.T @ est[:3, :3], [0.1, 0.0, 0.7]) @ half
    assert metrics.heading_offset_deg(truth, est, vertical, np.stack([np.eye(4), half])) == pytest.approx(20.0)
