"""The paper's ICP baseline (Desingh et al. 2016, Sec. V-B) on open3d.

Per object: the depth points of its segment (the largest plane, the table, removed first), registered with
point-to-point ICP against points sampled on the object's model, from ``n_starts`` initial poses around the
segment centroid oriented by the segment's principal axes; the best fit is kept (fitness, then inlier RMSE).
The paper segmented by hand; here the ground-truth visibility masks stand in for that. ICP knows nothing about
physics or the other objects, which is what the comparison is about.

Registration runs segment -> model: every observed point must lie on the model, while most model points are on
the far side and were never seen, so model -> segment fitness would reward poses that hide the model's back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import trimesh

from workbench.errors import InputError
from workbench.geometry import backproject, invert_pose, make_pose, transform_points
from workbench.problem.scene import Frame, ObjectModel
from workbench.problem.support import ransac_plane
from workbench.score.metrics import box_symmetries
from workbench.synth import visible_masks


@dataclass(frozen=True)
class IcpConfig:
    """Lengths in metres."""

    model_points: int = 2000  # surface samples of each model
    voxel: float = 0.005  # segment downsampling; keeps 50 ICP runs per object fast
    plane_threshold: float = 0.008  # RANSAC inlier distance of the table plane
    plane_iterations: int = 500
    start_spread: float = 0.02  # initial positions: uniform in a cube of this half-width (plus a push back)
    coarse_distance: float = 0.03  # ICP correspondence distance, first pass (catches a start a few cm off)
    fine_distance: float = 0.008  # second pass and the fitness/RMSE that rank the fits
    max_iterations: int = 30
    refine: int = 5  # starts refined at fine_distance after the coarse pass
    min_points: int = 10  # fewer segment points than this counts as "not seen"


@dataclass
class IcpFit:
    """The result for one object. ``fitness``: fraction of segment points within ``fine_distance`` of the fitted
    model; ``rmse`` of those (m). ``n_points`` 0 marks an unseen object whose pose is only a placeholder."""

    T_cam_obj: np.ndarray
    fitness: float
    rmse: float
    n_points: int


def plane_mask(points: np.ndarray, valid: np.ndarray, cfg: IcpConfig, rng: np.random.Generator) -> np.ndarray:
    """Pixels on the largest plane (seeded RANSAC, so the baseline repeats). points (H, W, 3), valid (H, W) ->
    (H, W) bool."""
    p = points[valid]
    n, d = ransac_plane(p, cfg.plane_threshold, cfg.plane_iterations, rng)
    mask = np.zeros(valid.shape, dtype=bool)
    mask[valid] = np.abs(p @ n + d) < cfg.plane_threshold
    return mask


def principal_axes(points: np.ndarray) -> np.ndarray:
    """Rotation whose columns are the principal axes of the points, largest variance first. (N, 3) -> (3, 3)."""
    centred = points - points.mean(axis=0)
    _, vecs = np.linalg.eigh(centred.T @ centred)
    R = vecs[:, ::-1]
    if np.linalg.det(R) < 0:
        R[:, 2] = -R[:, 2]
    return R


def initial_poses(segment: np.ndarray, model_pts: np.ndarray, T_cam_world: np.ndarray | None, n: int,
                  rng: np.random.Generator, cfg: IcpConfig) -> np.ndarray:
    """``n`` starting T_cam_obj: the model's principal axes put onto the segment's, under each of the 24 axis
    flips/permutations in turn (a partial view's axes are ambiguous), at random positions around the segment
    centroid pushed back along the line of sight (the seen surface is in front of the object's centre), kept
    above the table when it is known. segment (N, 3), model_pts (M, 3) camera/object frame -> (n, 4, 4)."""
    R_seg, R_model = principal_axes(segment), principal_axes(model_pts)
    flips = box_symmetries(np.ones(3))[:, :3, :3]  # the cube's 24 rotations: every axis permutation and flip
    centroid = segment.mean(axis=0)
    sight = centroid / np.linalg.norm(centroid)
    size = np.ptp(model_pts, axis=0)
    T_world_cam = None if T_cam_world is None else invert_pose(T_cam_world)
    out = np.empty((n, 4, 4))
    for i in range(n):
        R = R_seg @ flips[i % len(flips)] @ R_model.T
        p = centroid + sight * rng.uniform(0, 0.5 * size.max()) + rng.uniform(-1, 1, size=3) * cfg.start_spread
        if T_world_cam is not None:
            p_world = transform_points(T_world_cam, p)
            p_world[2] = max(p_world[2], 0.5 * size.min())
            p = transform_points(T_cam_world, p_world)
        out[i] = make_pose(R, p - R @ model_pts.mean(axis=0))
    return out


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))


def _rank(result) -> tuple[float, float]:
    """Sort key of an open3d registration result: fitness to 1 %, then the tighter fit."""
    return round(result.fitness, 2), -result.inlier_rmse


def fit_object(segment: np.ndarray, mesh: trimesh.Trimesh, T_cam_world: np.ndarray | None, n_starts: int,
               rng: np.random.Generator, cfg: IcpConfig) -> IcpFit:
    """Best ICP fit of a model to its segment (N, 3) over ``n_starts`` starts."""
    model_pts, _ = trimesh.sample.sample_surface(mesh, cfg.model_points, seed=int(rng.integers(2**31)))
    target = _cloud(model_pts)
    source = _cloud(segment).voxel_down_sample(cfg.voxel)
    reg = o3d.pipelines.registration
    p2p = reg.TransformationEstimationPointToPoint()
    crit = reg.ICPConvergenceCriteria(1e-6, 1e-6, cfg.max_iterations)
    # Every start gets a coarse pass; only the most promising few are refined (ranking as for the final choice).
    coarse = []
    for T_init in initial_poses(segment, model_pts, T_cam_world, n_starts, rng, cfg):
        # Registering segment -> model estimates T_obj_cam.
        T = reg.registration_icp(source, target, cfg.coarse_distance, invert_pose(T_init), p2p, crit).transformation
        ev = reg.evaluate_registration(source, target, cfg.fine_distance, T)
        coarse.append((_rank(ev), T))
    coarse.sort(key=lambda c: c[0], reverse=True)
    best, best_key = None, None
    for _, T in coarse[: cfg.refine]:
        fine = reg.registration_icp(source, target, cfg.fine_distance, T, p2p, crit)
        if best_key is None or _rank(fine) > best_key:
            best_key = _rank(fine)
            best = IcpFit(invert_pose(np.asarray(fine.transformation)), fine.fitness, fine.inlier_rmse, len(segment))
    return best


def placeholder_pose(mesh: trimesh.Trimesh, T_cam_world: np.ndarray | None, table_points: np.ndarray) -> np.ndarray:
    """Pose for an object nobody saw: resting unrotated at the table centre (the centroid of the table points
    when the table frame is unknown). -> T_cam_obj (4, 4)."""
    lo, hi = mesh.bounds
    centre_offset = 0.5 * (lo + hi)
    if T_cam_world is not None:
        T_world_obj = make_pose(np.eye(3), np.array([0.0, 0.0, -lo[2]]) - centre_offset * [1, 1, 0])
        return T_cam_world @ T_world_obj
    centre = table_points.mean(axis=0) if len(table_points) else np.array([0.0, 0.0, 1.0])
    return make_pose(np.eye(3), centre - centre_offset)


def estimate_icp_fits(
    frame: Frame,
    models: dict[int, ObjectModel],
    masks: dict[int, np.ndarray] | None = None,
    T_cam_world: np.ndarray | None = None,
    n_starts: int = 50,
    seed: int = 0,
    cfg: IcpConfig = IcpConfig(),
) -> dict[int, IcpFit]:
    """ICP fits of every object in ``frame.object_ids``, keyed by obj_id (see :func:`estimate_icp`)."""
    K = frame.camera.K
    missing = [i for i in frame.object_ids if i not in models]
    if missing:
        raise InputError("models", f"no model for obj_id {missing}")
    if masks is None:
        if frame.gt_T_cam_obj is None:
            raise InputError(frame.source, "the ICP baseline needs segmentation masks or ground truth to make them")
        meshes = [models[i].mesh for i in frame.object_ids]
        vis = visible_masks(K, frame.camera.width, frame.camera.height, meshes, frame.gt_T_cam_obj)
        masks = {obj_id: vis[k] for k, obj_id in enumerate(frame.object_ids)}
    if T_cam_world is None:
        T_cam_world = frame.camera.T_cam_world
    rng = np.random.default_rng(seed)
    points = backproject(frame.depth, K)
    valid = frame.depth > 0
    on_plane = plane_mask(points, valid, cfg, rng)
    fits = {}
    for obj_id in frame.object_ids:
        seg = masks[obj_id] & valid & ~on_plane
        mesh = models[obj_id].mesh
        if seg.sum() < cfg.min_points:
            T = placeholder_pose(mesh, T_cam_world, points[on_plane])
            fits[obj_id] = IcpFit(T, 0.0, np.inf, 0)
        else:
            fits[obj_id] = fit_object(points[seg], mesh, T_cam_world, n_starts, rng, cfg)
    return fits


def estimate_icp(
    frame: Frame,
    models: dict[int, ObjectModel],
    masks: dict[int, np.ndarray] | None = None,
    T_cam_world: np.ndarray | None = None,
    n_starts: int = 50,
    seed: int = 0,
) -> dict[int, np.ndarray]:
    """The ICP baseline's T_cam_obj (4, 4) per obj_id.

    ``masks``: obj_id -> (H, W) bool visible pixels (the segmentation); None renders them from the frame's ground
    truth. ``T_cam_world``: the table frame (default the camera's), used to keep starts above the table and to
    park unseen objects at the table centre (their :class:`IcpFit` has ``n_points`` 0 and fitness 0).
    """
    fits = estimate_icp_fits(frame, models, masks, T_cam_world, n_starts, seed)
    return {obj_id: f.T_cam_obj for obj_id, f in fits.items()}
