"""Local refinement: ICP (point-to-plane) of one object against the observed points near it.

It is a proposal like any other: the refined scene is projected by physics and weighed, and in PI-MCPF accepted
or rejected. ICP is deterministic, so the proposal adds a small Gaussian jitter around the ICP result; its
log-q correction needs the ICP result from the proposed pose too (the reverse move), which costs a second ICP.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from workbench.geometry import euler_to_matrix, invert_pose, make_pose, rotation_angle
from workbench.inference.proposal import Proposal, pick_objects
from workbench.inference.scenepoints import ModelSamples

STAGES = (0.04, 0.02, 0.01)  # m; correspondence distances, coarse to fine
JITTER_POS = 0.003  # m
MAX_POINTS = 400
JITTER_ANG = np.radians(1.5)


def crop(points: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """The points (P, 3) within ``radius`` (horizontally) of ``centre`` (3,) -> (Q, 3)."""
    return points[np.linalg.norm(points[:, :2] - centre[:2], axis=1) < radius]


def icp(scene: np.ndarray, samples: ModelSamples, T_init: np.ndarray, iterations: int = 8
        ) -> tuple[np.ndarray, int]:
    """Fit the model (samples in its object frame) at ``T_init`` (4, 4, table frame) to the observed points
    ``scene`` (P, 3): scene-to-model point-to-plane ICP, coarse to fine over ``STAGES`` -> (refined pose (4, 4),
    scene points within the last stage's distance of the model). Points of other objects in the crop find no
    model surface within the correspondence distance. Plain numpy and a k-d tree: bit-reproducible, unlike a
    multi-threaded ICP, so seeded runs stay identical."""
    if len(scene) < 10:
        return T_init.copy(), 0
    if len(scene) > MAX_POINTS:  # evenly thinned: a few hundred points pin a pose down as well as thousands
        scene = scene[np.linspace(0, len(scene) - 1, MAX_POINTS).astype(int)]
    tree = cKDTree(samples.points)
    T_obj_world = invert_pose(T_init)  # scene points are moved into the object frame; the model stays put
    inliers = 0
    for dist in STAGES:
        for _ in range(iterations):
            p = scene @ T_obj_world[:3, :3].T + T_obj_world[:3, 3]
            d, j = tree.query(p, distance_upper_bound=dist)
            ok = np.isfinite(d)
            inliers = int(ok.sum())
            if inliers < 6:
                return invert_pose(T_obj_world), inliers
            delta = _point_to_plane_step(p[ok], samples.points[j[ok]], samples.normals[j[ok]])
            T_obj_world = delta @ T_obj_world
            if np.linalg.norm(delta[:3, 3]) < 1e-5 and rotation_angle(delta[:3, :3]) < 1e-4:
                break
    return invert_pose(T_obj_world), inliers


def _point_to_plane_step(p: np.ndarray, q: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The small rigid motion (4, 4) that best moves points p (M, 3) onto the planes through q (M, 3) with
    normals n (M, 3), linearised: minimise sum(((R p + t - q) . n)^2) with R = I + [w]x."""
    A = np.concatenate([np.cross(p, n), n], axis=1)  # (M, 6)
    b = np.einsum("md,md->m", q - p, n)
    x, *_ = np.linalg.lstsq(A.T @ A + 1e-9 * np.eye(6), A.T @ b, rcond=None)
    return make_pose(euler_to_matrix(x[:3]), x[3:])


def _log_kernel(T: np.ndarray, centre: np.ndarray) -> float:
    """log of the (unnormalised) jitter density of pose T around ``centre`` (both (4, 4)); the normalisers are
    the same for the forward and reverse moves and cancel."""
    d = np.sum((T[:3, 3] - centre[:3, 3]) ** 2)
    a = float(rotation_angle(T[:3, :3].T @ centre[:3, :3]))
    return -0.5 * d / JITTER_POS**2 - 0.5 * a * a / JITTER_ANG**2


def jitter(rng: np.random.Generator, T: np.ndarray) -> np.ndarray:
    """A small Gaussian perturbation of pose T (4, 4)."""
    out = T.copy()
    out[:3, 3] += rng.normal(scale=JITTER_POS, size=3)
    out[:3, :3] = euler_to_matrix(rng.normal(scale=JITTER_ANG, size=3)) @ T[:3, :3]
    return out


def propose_icp(rng: np.random.Generator, parents: np.ndarray, points: np.ndarray, samples: list[ModelSamples],
                reach: np.ndarray, weights: np.ndarray) -> Proposal:
    """One object per particle (drawn by ``weights`` (K,)) is fitted by ICP to the observed points ``points``
    (P, 3) within its horizontal ``reach`` (K,) + 2 cm, then jittered. (B, K, 4, 4) -> Proposal."""
    out = parents.copy()
    log_q = np.zeros(len(parents))
    for b, k in enumerate(pick_objects(rng, len(parents), weights)):
        T0 = parents[b, k]
        fitted, _ = icp(crop(points, T0[:3, 3], reach[k] + 0.02), samples[k], T0)
        new = jitter(rng, fitted)
        back, _ = icp(crop(points, new[:3, 3], reach[k] + 0.02), samples[k], new)
        out[b, k] = new
        log_q[b] = _log_kernel(T0, back) - _log_kernel(new, fitted)
    return Proposal(out, log_q)
