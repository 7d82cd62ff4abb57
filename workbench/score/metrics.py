"""Pose-error metrics for one object, and the convergence count of the paper's Table II.

All poses are 4x4 float64. ``symmetries`` are (S, 4, 4) object-frame transforms under which the object looks the
same (identity included), as in :class:`workbench.problem.scene.ObjectModel`. A ground-truth pose ``T`` and ``T @ S_k``
are the same physical state, so the angular metrics compare the estimate with the closest of them.
Angles are returned in degrees, lengths in metres.
"""

from __future__ import annotations

import itertools

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from workbench.geometry import make_pose, matrix_to_euler, rotation_angle


def box_symmetries(extents: np.ndarray, tol: float = 1e-4) -> np.ndarray:
    """Proper rotations of a box centred at its origin that map it onto itself. (3,) metres -> (S, 4, 4).

    S = 4 with three different sides (the 180-degree turns about the face axes), 8 with two equal sides,
    24 for a cube. Identity first.
    """
    e = np.asarray(extents, dtype=np.float64)
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[np.arange(3), perm] = signs
            # R maps axis perm[i] onto axis i, so the box is unchanged when those axes have equal length.
            if np.linalg.det(R) > 0 and np.all(np.abs(e[list(perm)] - e) <= tol):
                out.append(make_pose(R, np.zeros(3)))
    out.sort(key=lambda T: -np.trace(T))  # identity (trace 4) first
    return np.stack(out)


def position_error(T_gt: np.ndarray, T_est: np.ndarray, symmetries: np.ndarray | None = None) -> float:
    """Distance (m) between the estimate's origin and that of the ground-truth equivalent closest in rotation
    (``closest_symmetric``, as ``rotation_error`` measures against). A symmetry of a model whose origin is off its
    centre moves the origin: YCB-Video's wood block turned upside down is the same block 3.5 cm from the origin."""
    T_sym = closest_symmetric(T_gt, T_est, symmetries)
    return float(np.linalg.norm(T_sym[:3, 3] - np.asarray(T_est)[:3, 3]))


def closest_symmetric(T_gt: np.ndarray, T_est: np.ndarray, symmetries: np.ndarray | None = None) -> np.ndarray:
    """The ground-truth equivalent ``T_gt @ S_k`` whose rotation is closest to the estimate's. -> (4, 4)."""
    sym = np.eye(4)[None] if symmetries is None else np.asarray(symmetries, dtype=np.float64)
    cands = np.asarray(T_gt, dtype=np.float64) @ sym
    R_est = np.asarray(T_est, dtype=np.float64)[:3, :3]
    angles = rotation_angle(np.swapaxes(cands[:, :3, :3], -1, -2) @ R_est)
    return cands[int(np.argmin(angles))]


def rotation_error(T_gt: np.ndarray, T_est: np.ndarray, symmetries: np.ndarray | None = None) -> float:
    """Geodesic angle (deg) between the estimate and the closest symmetric equivalent of the ground truth."""
    T_sym = closest_symmetric(T_gt, T_est, symmetries)
    return float(np.degrees(rotation_angle(T_sym[:3, :3].T @ np.asarray(T_est)[:3, :3])))


RIGHT_CM, RIGHT_DEG = 2.0, 10.0  # an estimate is right within these, up to the model's symmetries


def is_right(T_gt: np.ndarray, T_est: np.ndarray, symmetries: np.ndarray | None = None) -> bool:
    """Whether the estimate lies within RIGHT_CM (``position_error``) and RIGHT_DEG (``rotation_error``) of the
    ground truth, up to its ``symmetries``: the tolerances every benchmark counts objects right by."""
    return (100 * position_error(T_gt, T_est, symmetries) < RIGHT_CM
            and rotation_error(T_gt, T_est, symmetries) < RIGHT_DEG)


def heading_offset_deg(T_gt: np.ndarray, T_est: np.ndarray, vertical: np.ndarray,
                       symmetries: np.ndarray | None = None) -> float:
    """How far (degrees, in (-180, 180]) the ground truth is turned about ``vertical`` (3,), unit, in the poses'
    frame, from the estimate: the signed angle between the two poses' model axis that is most nearly horizontal in
    the estimate, both projected on the plane normal to ``vertical`` (the truth's symmetric equivalent nearest the
    estimate). What a reported range of headings (``posterior.ObjectPosterior.yaw_range_deg``) is checked by."""
    v = np.asarray(vertical, dtype=np.float64) / np.linalg.norm(vertical)
    T_gt = closest_symmetric(T_gt, T_est, symmetries)
    axis = int(np.argmin(np.abs(v @ np.asarray(T_est)[:3, :3])))
    a, b = (np.asarray(T)[:3, axis] - v * (v @ np.asarray(T)[:3, axis]) for T in (T_est, T_gt))
    return float(np.degrees(np.arctan2(v @ np.cross(a, b), a @ b)))


def rpy_errors(T_gt: np.ndarray, T_est: np.ndarray, symmetries: np.ndarray | None = None) -> np.ndarray:
    """|roll|, |pitch|, |yaw| errors (deg) about the x, y, z axes of the frame the poses are in (the table frame).

    They are the Euler angles of ``R_est @ R_gt'^T``, the rotation in the table frame that carries the closest
    symmetric ground truth ``R_gt'`` onto the estimate. Differencing the two poses' own Euler angles instead would
    blow up near pitch = +-90 degrees, which every box lying on its side is. -> (3,)
    """
    T_sym = closest_symmetric(T_gt, T_est, symmetries)
    delta = np.asarray(T_est)[:3, :3] @ T_sym[:3, :3].T
    return np.abs(np.degrees(matrix_to_euler(delta)))


def model_points(mesh: trimesh.Trimesh, n: int = 1000, seed: int = 0) -> np.ndarray:
    """Points for ADD-S / MSSD: the mesh vertices (where a box's largest distances occur) plus ``n`` surface
    samples. -> (V + n, 3) metres."""
    samples, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.concatenate([np.asarray(mesh.vertices, dtype=np.float64), np.asarray(samples, dtype=np.float64)])


def _apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def add_s(T_gt: np.ndarray, T_est: np.ndarray, points: np.ndarray) -> float:
    """ADD-S (m): mean over the ground-truth model points of the distance to the closest estimated point.
    ``points``: (N, 3) in the object frame."""
    gt = _apply(np.asarray(T_gt, dtype=np.float64), points)
    est = _apply(np.asarray(T_est, dtype=np.float64), points)
    d, _ = cKDTree(est).query(gt, k=1)
    return float(np.mean(d))


def mssd(T_gt: np.ndarray, T_est: np.ndarray, points: np.ndarray, symmetries: np.ndarray | None = None) -> float:
    """BOP's maximum symmetry-aware surface distance (m): min over symmetries S of max_x |T_est x - T_gt S x|.
    ``points``: (N, 3) in the object frame (include the vertices: the maximum is at one)."""
    sym = np.eye(4)[None] if symmetries is None else np.asarray(symmetries, dtype=np.float64)
    est = _apply(np.asarray(T_est, dtype=np.float64), points)
    best = np.inf
    for S in sym:
        gt = _apply(np.asarray(T_gt, dtype=np.float64) @ S, points)
        best = min(best, float(np.max(np.linalg.norm(est - gt, axis=-1))))
    return best


def iterations_to_converge(
    best_poses_history: np.ndarray,
    pos_tol: float = 0.01,
    rot_tol_deg: float = 3.0,
    symmetries: list[np.ndarray] | None = None,
) -> int:
    """How many iterations the estimate needed to settle (the paper's Table II).

    ``best_poses_history``: (T, K, 4, 4), entry t the best particle's poses of the K objects after iteration t
    (index 0 = the first iteration). One step is the move from iteration s to s + 1; it is *small* when every
    object moves less than ``pos_tol`` metres and ``rot_tol_deg`` degrees (symmetry-aware when ``symmetries``,
    one (S, 4, 4) array per object, is given: a box flipping to an identical-looking pose has not moved).

    Returns the smallest t such that every step from iteration t onward is small: the estimate after iteration
    t is already within tolerance of each later one, step by step. Returns T when the last step is not small
    (not converged within the history); 0 when every step is small.
    """
    H = np.asarray(best_poses_history, dtype=np.float64)
    T, K = H.shape[:2]
    small = np.ones(max(T - 1, 0), dtype=bool)
    for s in range(T - 1):
        for k in range(K):
            sym = None if symmetries is None else symmetries[k]
            moved_far = position_error(H[s, k], H[s + 1, k], sym) >= pos_tol
            turned = rotation_error(H[s, k], H[s + 1, k], sym) >= rot_tol_deg
            if moved_far or turned:
                small[s] = False
                break
    if T > 1 and not small[-1]:
        return T
    big = np.flatnonzero(~small)
    return 0 if big.size == 0 else int(big[-1] + 1)
