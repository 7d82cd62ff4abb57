"""Local refinement: ICP (point-to-plane) of one object against the observed points near it.

It is a proposal like any other: the refined scene is projected by physics and weighed, and in PI-MCPF accepted
or rejected. ICP is deterministic, so the proposal adds a small Gaussian jitter around the ICP result; its
log-q correction needs the ICP result from the proposed pose too (the reverse move), which costs a second ICP;
PI-PF, which never uses the correction, skips it.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from workbench.geometry import euler_to_matrix, invert_pose, make_pose, rotation_angle
from workbench.inference.search.moves.proposal import Proposal, pick_objects
from workbench.inference.search.scenepoints import ModelSamples, ScenePoints

STAGES = (0.04, 0.02, 0.01)  # m; correspondence distances, coarse to fine
JITTER_POS = 0.003  # m
MAX_POINTS = 400
PROPOSAL_POINTS = 200  # per ICP move: a refinement from near the object needs fewer than a fit
NEAR = 0.02  # m; an object is fitted to the observed points within its horizontal reach plus this
STILL_M, STILL_RAD = 1e-4, 1e-3  # a step this small (0.1 mm, 0.06 degrees) ends a stage
JITTER_ANG = np.radians(1.5)
# A scene point and a model sample whose normals differ by more than 60 degrees are no correspondence: a box's
# vertical side beside a pair of scissors lying flat is not their top. Without it, ICP from the true pose of the
# generated frames' scissors went 14 cm away, pulled by a neighbour's side (docs/journal/2026-11.md, "Observed
# normals").
NORMAL_AGREEMENT = np.cos(np.radians(60.0))


def icp(scene: np.ndarray, samples: ModelSamples, T_init: np.ndarray, iterations: int = 8
        ) -> tuple[np.ndarray, int]:
    """Fit the model (samples in its object frame) at ``T_init`` (4, 4, table frame) to the observed points
    ``scene`` (P, 3) -> (refined pose (4, 4), scene points within the last stage's distance of the model).
    One start of ``icp_batch``."""
    T, inliers = icp_batch([scene], samples, T_init[None], iterations)
    return T[0], int(inliers[0])


def icp_batch(scenes: list[np.ndarray], samples: ModelSamples, T_init: np.ndarray, iterations: int = 8,
              max_points: int = MAX_POINTS, stages: tuple[float, ...] = STAGES,
              viewpoint: np.ndarray | None = None, normals: list[np.ndarray] | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Fit one model (samples in its object frame) from S starts at once: start s at ``T_init[s]`` (4, 4, table
    frame) against its observed points ``scenes[s]`` (P_s, 3). Scene-to-model point-to-plane ICP, coarse to
    fine over the correspondence distances ``stages`` (m); a start leaves a stage when its step is negligible and
    stops where fewer than 6 points find the model. -> (refined poses (S, 4, 4), inliers (S,): scene points
    within the last stage's distance).

    Points of other objects in a crop find no model surface within the correspondence distance. All starts share
    one k-d tree query and one batched solve per step, so a library of thousands of starts costs a few dozen
    numpy calls per step instead of thousands. Plain numpy and a k-d tree: bit-reproducible, unlike a
    multi-threaded ICP, so seeded runs stay identical.

    ``viewpoint`` (3,), the camera centre in the table frame: a scene point matched to the model's far side (a
    surface facing away from the camera, which the sensor cannot have seen) is no correspondence. Without it, an
    object lying on another pulls its hidden bottom onto the other's top: from its true pose, YCB-Video's pudding
    box on the wood block slid 6 cm and turned 74 degrees.

    ``normals``: per scene, the observed surface's unit normals at its points (P_s, 3), table frame
    (``ScenePoints.normals``): a scene point whose normal differs from its model sample's by more than 60 degrees
    is no correspondence either (``NORMAL_AGREEMENT``)."""
    S = len(scenes)
    if S == 0:
        return np.zeros((0, 4, 4)), np.zeros(0, dtype=int)
    # Scene points are moved into the object frame; the model (its k-d tree) stays put.
    T_obj_world = invert_pose(np.asarray(T_init, dtype=np.float64)).reshape(S, 4, 4)
    # Evenly thinned: a few hundred points pin a pose down as well as thousands. Starts at one place share their
    # points (``near``), so the picks are made once per length.
    picks: dict[int, np.ndarray] = {}
    for sc in scenes:
        if len(sc) > max_points and len(sc) not in picks:
            picks[len(sc)] = np.linspace(0, len(sc) - 1, max_points).astype(int)
    every = [picks.get(len(sc), slice(None)) for sc in scenes]
    thin = [sc[i] for sc, i in zip(scenes, every)]
    sizes = np.array([len(sc) for sc in thin])
    inliers = np.zeros(S, dtype=int)
    alive = sizes >= 10  # fewer points cannot pin a pose: such starts stay where they are
    if not alive.any():
        return invert_pose(T_obj_world), inliers
    points = np.concatenate(thin)
    scene_normals = None if normals is None else np.concatenate([n[i] for n, i in zip(normals, every)])
    owner = np.repeat(np.arange(S), sizes)
    tree = cKDTree(samples.points)
    for dist in stages:
        moving = alive.copy()
        for _ in range(iterations):
            if not moving.any():
                break
            sel = moving[owner]
            own = owner[sel]
            R, t = T_obj_world[own, :3, :3], T_obj_world[own, :3, 3]
            p = np.einsum("nij,nj->ni", R, points[sel]) + t
            d, j = tree.query(p, distance_upper_bound=dist)
            ok = np.isfinite(d)
            jj = np.where(ok, j, 0)
            if viewpoint is not None:
                eye = np.einsum("nij,j->ni", R, viewpoint) + t  # the camera centre in the object frame
                ok &= np.einsum("nd,nd->n", samples.normals[jj], eye - samples.points[jj]) > 0
            if scene_normals is not None:
                n_obj = np.einsum("nij,nj->ni", R, scene_normals[sel])  # the scene's normals in the object frame
                ok &= np.einsum("nd,nd->n", samples.normals[jj], n_obj) > NORMAL_AGREEMENT
            count = np.bincount(own[ok], minlength=S)
            inliers[moving] = count[moving]
            lost = moving & (count < 6)
            alive &= ~lost
            moving &= ~lost
            keep = ok & moving[own]
            if not keep.any():
                break
            delta = _point_to_plane_steps(p[keep], samples.points[j[keep]], samples.normals[j[keep]], own[keep], S)
            T_obj_world[moving] = delta[moving] @ T_obj_world[moving]
            moving &= ~((np.linalg.norm(delta[:, :3, 3], axis=1) < STILL_M)
                        & (rotation_angle(delta[:, :3, :3]) < STILL_RAD))
    return invert_pose(T_obj_world), inliers


def _point_to_plane_steps(p: np.ndarray, q: np.ndarray, n: np.ndarray, owner: np.ndarray, S: int) -> np.ndarray:
    """Per start s, the small rigid motion (4, 4) that best moves its points p (M, 3) (those with ``owner`` (M,),
    non-decreasing, == s) onto the planes through q (M, 3) with normals n (M, 3), linearised: minimise
    sum(((R p + t - q) . n)^2) with R = I + [w]x. -> (S, 4, 4); identity for starts without points."""
    A = np.concatenate([np.cross(p, n), n], axis=1)  # (M, 6)
    b = np.einsum("md,md->m", q - p, n)
    # Per-start sums of the normal equations' entries, as one sparse (S, M) indicator product. ``owner`` is sorted
    # (points are grouped by start), so the rows' extents are where each start's run begins: built directly in
    # CSR form, a third cheaper than from coordinates, and the same matrix.
    rows = np.searchsorted(owner, np.arange(S + 1))
    member = csr_matrix((np.ones(len(owner)), np.arange(len(owner)), rows), shape=(S, len(owner)))
    AtA = member @ (A[:, :, None] * A[:, None, :]).reshape(-1, 36)
    Atb = member @ (A * b[:, None])
    x = np.linalg.solve(AtA.reshape(S, 6, 6) + 1e-9 * np.eye(6), Atb[..., None])[..., 0]
    return make_pose(euler_to_matrix(x[:, :3]), x[:, 3:])


def _log_kernel(T: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """log of the (unnormalised) jitter density of poses T around ``centre`` (both (B, 4, 4)) -> (B,); the
    normalisers are the same for the forward and reverse moves and cancel."""
    d = np.sum((T[:, :3, 3] - centre[:, :3, 3]) ** 2, axis=1)
    a = rotation_angle(np.swapaxes(T[:, :3, :3], 1, 2) @ centre[:, :3, :3])
    return -0.5 * d / JITTER_POS**2 - 0.5 * a * a / JITTER_ANG**2


def jitter(rng: np.random.Generator, T: np.ndarray) -> np.ndarray:
    """Small Gaussian perturbations of poses T (B, 4, 4) -> (B, 4, 4)."""
    out = T.copy()
    out[:, :3, 3] += rng.normal(scale=JITTER_POS, size=(len(T), 3))
    out[:, :3, :3] = euler_to_matrix(rng.normal(scale=JITTER_ANG, size=(len(T), 3))) @ T[:, :3, :3]
    return out


def crops(points: np.ndarray, centres: np.ndarray, radius: float) -> list[np.ndarray]:
    """For each centre (S, 2 or 3), the indices of the points (P, 3) within ``radius`` of it horizontally, in their
    original order -> S arrays (Q_s,) int."""
    tree = cKDTree(points[:, :2])
    return [np.asarray(i, dtype=int) for i in tree.query_ball_point(centres[:, :2], radius, return_sorted=True)]


def near(cloud: ScenePoints, centres: np.ndarray, radius: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """For each centre (S, 3), the observed points of ``cloud`` within ``radius`` (m) of it horizontally and their
    normals, as ``icp_batch`` takes them -> (S arrays (Q_s, 3), S arrays (Q_s, 3)); centres at the same x, y share
    their arrays (read them, do not write)."""
    places, at = np.unique(centres[:, :2], axis=0, return_inverse=True)  # a library's starts share a few places
    crop = crops(cloud.points, places, radius)
    points, normals = [cloud.points[i] for i in crop], [cloud.normals[i] for i in crop]
    return [points[a] for a in at.ravel()], [normals[a] for a in at.ravel()]


def refit(cloud: ScenePoints, samples: ModelSamples, reach: float, T: np.ndarray) -> np.ndarray:
    """Poses T (S, 4, 4) of one object of horizontal ``reach`` (m), each refined by ICP on PROPOSAL_POINTS of
    the observed points ``cloud`` near it, with their normals, seen from its viewpoint -> (S, 4, 4)."""
    points, normals = near(cloud, T[:, :3, 3], reach + NEAR)
    return icp_batch(points, samples, T, max_points=PROPOSAL_POINTS, viewpoint=cloud.viewpoint,
                     normals=normals)[0]


def propose_icp(rng: np.random.Generator, parents: np.ndarray, cloud: ScenePoints, samples: list[ModelSamples],
                reach: np.ndarray, weights: np.ndarray, log_q: bool = True) -> Proposal:
    """One object per particle (drawn by ``weights`` (K,)) is fitted by ICP to the observed points ``cloud`` near
    it (``refit``; ``reach`` (K,) m), then jittered.
    (B, K, 4, 4) -> Proposal.

    All particles that move the same object are fitted as one ``icp_batch``. The log-q correction needs a second
    ICP from each proposed pose (the reverse move); ``log_q`` False skips it, for PI-PF, which never uses the
    correction, and gives NaN corrections instead."""
    B = len(parents)
    picks = pick_objects(rng, B, weights)
    rows = np.arange(B)
    T0 = parents[rows, picks]
    fitted = np.empty_like(T0)
    for k in np.unique(picks):
        sel = picks == k
        fitted[sel] = refit(cloud, samples[k], reach[k], T0[sel])
    new = jitter(rng, fitted)
    out = parents.copy()
    out[rows, picks] = new
    if not log_q:
        return Proposal(out, np.full(B, np.nan))
    back = np.empty_like(T0)
    for k in np.unique(picks):
        sel = picks == k
        back[sel] = refit(cloud, samples[k], reach[k], new[sel])
    return Proposal(out, _log_kernel(T0, back) - _log_kernel(new, fitted))
