import numpy as np

from workbench.geometry import (
    euler_to_matrix,
    invert_pose,
    matrix_to_euler,
    matrix_to_quat_wxyz,
    pose_from_xyz_rpy,
    pose_to_xyz_rpy,
    quat_wxyz_to_matrix,
    random_rotations,
    rot_x,
    rot_z,
    rotation_angle,
    rotvec_to_matrix,
    wxyz_to_xyzw,
    xyzw_to_wxyz,
)


def test_euler_roundtrip():
    rpy = np.random.default_rng(0).uniform([-3, -1.5, -3], [3, 1.5, 3], size=(100, 3))
    assert np.allclose(matrix_to_euler(euler_to_matrix(rpy)), rpy)


def test_euler_is_extrinsic_xyz():
    R = euler_to_matrix(np.array([0.0, 0.0, np.pi / 2]))
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0])


def test_rotation_vectors_turn_about_their_axis_by_their_length():
    assert np.allclose(rotvec_to_matrix([0.0, 0.0, 0.3]), rot_z(0.3))
    assert np.allclose(rotvec_to_matrix([-0.2, 0.0, 0.0]), rot_x(-0.2))
    assert np.allclose(rotvec_to_matrix(np.zeros(3)), np.eye(3))  # no turn, no division by zero
    rng = np.random.default_rng(2)
    v = rng.normal(size=(20, 3))
    v *= rng.uniform(0.0, 3.0, size=(20, 1)) / np.linalg.norm(v, axis=1, keepdims=True)  # angles below pi
    R = rotvec_to_matrix(v)
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3)) and np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(rotation_angle(R), np.linalg.norm(v, axis=1))
    assert np.allclose(np.einsum("nij,nj->ni", R, v), v)  # the axis stays put


def test_quaternion_roundtrip_and_order():
    R = random_rotations(np.random.default_rng(1), 50)
    assert np.allclose(quat_wxyz_to_matrix(matrix_to_quat_wxyz(R)), R)
    q = matrix_to_quat_wxyz(rot_z(np.pi / 2))  # w = cos(45 deg), z = sin(45 deg)
    assert np.allclose(q, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)])
    assert np.allclose(xyzw_to_wxyz(wxyz_to_xyzw(q)), q)


def test_pose_inverse_and_xyz_rpy():
    v = np.array([0.1, -0.2, 0.3, 0.4, -0.5, 0.6])
    T = pose_from_xyz_rpy(v)
    assert np.allclose(T @ invert_pose(T), np.eye(4))
    assert np.allclose(pose_to_xyz_rpy(T), v)
