"""Rigid-body geometry: poses, rotations and the conversions between their forms.

Conventions (see README, "Conventions"):
- A pose is a 4x4 homogeneous matrix ``T_a_b`` (float64) mapping points in frame b to frame a.
- Lengths are metres, angles radians.
- Euler angles are (roll, pitch, yaw), extrinsic about the table's x, y, z axes:
  ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
- Quaternions are (w, x, y, z), as viser uses. pybullet's (x, y, z, w) appears only in ``physics/world.py``.
All functions accept leading batch dimensions ``(...)``.
"""

from __future__ import annotations

import numpy as np

from workbench.errors import InputError

# Rotation and bottom-row tolerance of a rigid pose (``check_rigid``): files store rotations with ~6 digits, products
# of many rotations drift by ~1e-12.
RIGID_TOLERANCE = 1e-3


def rot_x(a: np.ndarray | float) -> np.ndarray:
    """Rotation about x. ``a``: (...) -> (..., 3, 3)."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([o, z, z, z, c, -s, z, s, c], axis=-1).reshape(a.shape + (3, 3))


def rot_y(a: np.ndarray | float) -> np.ndarray:
    """Rotation about y. ``a``: (...) -> (..., 3, 3)."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([c, z, s, z, o, z, -s, z, c], axis=-1).reshape(a.shape + (3, 3))


def rot_z(a: np.ndarray | float) -> np.ndarray:
    """Rotation about z. ``a``: (...) -> (..., 3, 3)."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([c, -s, z, s, c, z, z, z, o], axis=-1).reshape(a.shape + (3, 3))


def euler_to_matrix(rpy: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) -> rotation. ``rpy``: (..., 3) -> (..., 3, 3)."""
    rpy = np.asarray(rpy, dtype=np.float64)
    return rot_z(rpy[..., 2]) @ rot_y(rpy[..., 1]) @ rot_x(rpy[..., 0])


def rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    """Rotation by ``|v|`` radians about the unit axis ``v / |v|`` (Rodrigues). ``v``: (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1)[..., None, None]
    k = v / np.maximum(angle[..., 0], 1e-300)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def matrix_to_euler(R: np.ndarray) -> np.ndarray:
    """Rotation -> (roll, pitch, yaw), pitch in [-pi/2, pi/2]. ``R``: (..., 3, 3) -> (..., 3)."""
    R = np.asarray(R, dtype=np.float64)
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    # At gimbal lock roll and yaw share one degree of freedom: put it all in yaw.
    locked = np.abs(R[..., 2, 0]) > 1.0 - 1e-9
    if np.any(locked):
        yaw = np.where(locked, np.arctan2(-R[..., 0, 1], R[..., 1, 1]), yaw)
        roll = np.where(locked, 0.0, roll)
    return np.stack([roll, pitch, yaw], axis=-1)


def pose_from_xyz_rpy(xyz_rpy: np.ndarray) -> np.ndarray:
    """(x, y, z, roll, pitch, yaw) -> pose. (..., 6) -> (..., 4, 4)."""
    xyz_rpy = np.asarray(xyz_rpy, dtype=np.float64)
    T = np.zeros(xyz_rpy.shape[:-1] + (4, 4))
    T[..., :3, :3] = euler_to_matrix(xyz_rpy[..., 3:6])
    T[..., :3, 3] = xyz_rpy[..., :3]
    T[..., 3, 3] = 1.0
    return T


def pose_to_xyz_rpy(T: np.ndarray) -> np.ndarray:
    """Pose -> (x, y, z, roll, pitch, yaw). (..., 4, 4) -> (..., 6)."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[..., :3, 3], matrix_to_euler(T[..., :3, :3])], axis=-1)


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rotation (..., 3, 3) and translation (..., 3) -> pose (..., 4, 4)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros(np.broadcast_shapes(R.shape[:-2], t.shape[:-1]) + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid pose. (..., 4, 4) -> (..., 4, 4)."""
    T = np.asarray(T, dtype=np.float64)
    R = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_pose(R, -(R @ T[..., :3, 3:4])[..., 0])


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply pose (4, 4) to points (..., 3) -> (..., 3)."""
    return p @ T[:3, :3].T + T[:3, 3]


def backproject(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points of every pixel (zero where there is no reading) of a depth image (H, W) m taken with
    intrinsics ``K`` (3, 3) -> (H, W, 3) m."""
    H, W = depth.shape
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    z = depth.astype(np.float64)
    return np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)


def quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> rotation. (..., 4) -> (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation -> unit quaternion (w, x, y, z) with w >= 0. (..., 3, 3) -> (..., 4)."""
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for i, m in enumerate(flat):
        # Shepperd's method: pivot on the largest diagonal term for numerical stability.
        tr = np.trace(m)
        k = int(np.argmax([tr, m[0, 0], m[1, 1], m[2, 2]]))
        if k == 0:
            s = 2.0 * np.sqrt(1.0 + tr)
            q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif k == 1:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif k == 2:
            s = 2.0 * np.sqrt(1.0 - m[0, 0] + m[1, 1] - m[2, 2])
            q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 - m[0, 0] - m[1, 1] + m[2, 2])
            q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
        q = np.asarray(q)
        out[i] = q if q[0] >= 0 else -q
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    return out.reshape(R.shape[:-2] + (4,))


def wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """(..., 4) wxyz -> xyzw (pybullet's order)."""
    q = np.asarray(q)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """(..., 4) xyzw (pybullet's order) -> wxyz."""
    q = np.asarray(q)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle of a rotation in radians. (..., 3, 3) -> (...)."""
    tr = np.trace(np.asarray(R), axis1=-2, axis2=-1)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """Uniformly distributed rotations (Haar measure). -> (n, 3, 3)."""
    q = rng.normal(size=(n, 4))
    return quat_wxyz_to_matrix(q / np.linalg.norm(q, axis=-1, keepdims=True))


def principal_heading(points: np.ndarray) -> float:
    """Heading (rad) of the principal axis of the points' (P, 2 or 3) xy spread."""
    xy = points[:, :2] - points[:, :2].mean(axis=0)
    _, v = np.linalg.eigh(xy.T @ xy)
    return float(np.arctan2(v[1, -1], v[0, -1]))


def check_rigid(T, what: str, path=None) -> np.ndarray:
    """Poses (..., 4, 4) -> float64 copy, or InputError(path, ...) naming ``what`` when a pose is not finite,
    its rotation is not orthonormal with determinant +1 (a reflection), or its bottom row is not 0 0 0 1."""
    try:
        T = np.array(T, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(path, f"{what}: poses must be 4x4 matrices of numbers") from e
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise InputError(path, f"{what}: poses must be 4x4 matrices, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise InputError(path, f"{what}: a pose contains NaN or inf")
    if np.abs(T[..., 3, :] - [0.0, 0.0, 0.0, 1.0]).max(initial=0.0) > RIGID_TOLERANCE:
        raise InputError(path, f"{what}: the bottom row of a pose must be [0, 0, 0, 1]")
    R = T[..., :3, :3]
    # Entries of a rotation lie in [-1, 1]: checked first so that huge values are refused without overflowing.
    if np.abs(R).max(initial=0.0) > 1 + RIGID_TOLERANCE or \
            np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(initial=0.0) > RIGID_TOLERANCE:
        raise InputError(path, f"{what}: a rotation is not orthonormal")
    if np.any(np.linalg.det(R) < 0):
        raise InputError(path, f"{what}: a rotation has determinant -1 (a reflection, not a rotation)")
    return T
