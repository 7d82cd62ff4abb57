"""The observed points above the table, their clusters, and how well a scene explains them.

All on the problem's pixel grid (``Problem.render_camera``, ``Problem.observed``); points in the table frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from workbench.geometry import invert_pose, transform_points
from workbench.problem.problem import Problem

MIN_HEIGHT = 0.006  # m; lower points are the table (noise, unevenness)
EXPLAINED = 0.015  # m; an observed depth this close to a scene's surface is explained by it
SEEN_THROUGH = 0.02  # m; an observed depth this far behind an object's surface sees through where it should be
NORMAL_NEIGHBOURS = 12  # observed points whose plane gives a point's normal (a patch of about 5 mm at 1 m)
TABLE_CELL = 0.005  # m; the grid on which ``ScenePoints.table`` records where the bare table is seen


@dataclass(frozen=True)
class ScenePoints:
    """``points``: (P, 3) observed points above the table, table frame; ``pixels``: (P, 2) their (row, col) on the
    problem grid; ``viewpoint``: (3,) the camera centre they were seen from, table frame; ``normals``: (P, 3) unit
    normals of the observed surface at each point, facing the viewpoint (``point_normals``); ``table``: (T, 2) int
    the distinct TABLE_CELL cells (cell (i, j) spans [i, i + 1) * TABLE_CELL in x, [j, j + 1) in y) where the
    sensor sees the table's plane, within the table's extent: free space for a flat object's outline
    (``footprint``)."""

    points: np.ndarray
    pixels: np.ndarray
    viewpoint: np.ndarray
    normals: np.ndarray
    table: np.ndarray


@dataclass(frozen=True)
class ModelSamples:
    """Surface samples of one model for fitting and explanation tests: ``points`` (M, 3) and ``normals`` (M, 3),
    object frame, metres."""

    points: np.ndarray
    normals: np.ndarray


def model_samples(mesh: trimesh.Trimesh, n: int = 1500, seed: int = 0) -> ModelSamples:
    """Evenly spread surface points of ``mesh`` with their face normals (seeded, so the same for every run): about
    ``n``; thin parts (scissors, a clamp) get fewer, which trimesh would log as a WARNING per model and frame."""
    log = logging.getLogger("trimesh")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        points, faces = trimesh.sample.sample_surface_even(mesh, n, seed=seed)
    finally:
        log.setLevel(level)
    return ModelSamples(np.asarray(points, dtype=np.float64), np.asarray(mesh.face_normals[faces], dtype=np.float64))


def observed_points(problem: Problem, max_height: float = 0.45) -> ScenePoints:
    """Back-project the observed depth and keep what stands above the table, within the table's extent."""
    cam = problem.render_camera
    obs = problem.observed.astype(np.float64)
    rows, cols = np.nonzero(obs > 0)
    z = obs[rows, cols]
    K = cam.K
    p_cam = np.stack([(cols - K[0, 2]) / K[0, 0] * z, (rows - K[1, 2]) / K[1, 1] * z, z], axis=1)
    world = transform_points(invert_pose(cam.T_cam_world), p_cam)
    tb = problem.table
    inside = ((world[:, 0] >= tb.x_min) & (world[:, 0] <= tb.x_max)
              & (world[:, 1] >= tb.y_min) & (world[:, 1] <= tb.y_max))
    keep = inside & (world[:, 2] > MIN_HEIGHT) & (world[:, 2] < max_height)
    on_table = inside & (np.abs(world[:, 2]) <= MIN_HEIGHT)
    table = _distinct_cells(table_cells(world[on_table, :2]))
    eye = viewpoint(problem)
    return ScenePoints(world[keep], np.stack([rows[keep], cols[keep]], axis=1), eye, point_normals(world[keep], eye),
                       table)


def table_cells(xy: np.ndarray) -> np.ndarray:
    """The TABLE_CELL grid cells (N, 2) int of the points ``xy`` (N, 2) m: cell (i, j) spans [i, i + 1) * TABLE_CELL
    in x and [j, j + 1) * TABLE_CELL in y (``ScenePoints.table``'s grid)."""
    return np.floor(xy / TABLE_CELL).astype(np.int64)


def _distinct_cells(cells: np.ndarray) -> np.ndarray:
    """The distinct rows of integer ``cells`` (N, 2) -> (D, 2), sorted: ``np.unique(cells, axis=0)``, marked on a
    grid over their extent instead of sorted (a table's few hundred thousand readings: 2 ms, not 150)."""
    if len(cells) == 0:
        return cells.reshape(0, 2)
    lo = cells.min(axis=0)
    grid = np.zeros(tuple(cells.max(axis=0) - lo + 1), dtype=bool)
    grid[cells[:, 0] - lo[0], cells[:, 1] - lo[1]] = True
    return np.argwhere(grid) + lo


def point_normals(points: np.ndarray, eye: np.ndarray, neighbours: int = NORMAL_NEIGHBOURS) -> np.ndarray:
    """Unit normals (P, 3) of the surface through ``points`` (P, 3): the least-variance direction of each point's
    ``neighbours`` nearest points, turned to face ``eye`` (3,), the camera centre (a sensor sees only surfaces that
    face it). Where fewer points are given than ``neighbours``, all of them."""
    if len(points) == 0:
        return np.zeros((0, 3))
    _, idx = cKDTree(points).query(points, k=min(neighbours, len(points)))
    near = points[idx.reshape(len(points), -1)]
    near = near - near.mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("pki,pkj->pij", near, near))
    n = vectors[:, :, 0]  # eigh sorts ascending: the first is the least-variance direction
    n[np.einsum("pd,pd->p", n, eye - points) < 0] *= -1.0
    return n


def viewpoint(problem: Problem) -> np.ndarray:
    """The camera centre in the table frame -> (3,) m."""
    return invert_pose(problem.render_camera.T_cam_world)[:3, 3].copy()


def project_samples(problem: Problem, scene: np.ndarray, samples: list[ModelSamples]
                    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per object, its surface samples that face the camera, projected: (rows (M,), cols (M,), depth (M,) m),
    only those inside the grid."""
    cam = problem.render_camera
    h, w = problem.observed.shape
    out = []
    for k, s in enumerate(samples):
        T = cam.T_cam_world @ scene[k]
        p = s.points @ T[:3, :3].T + T[:3, 3]
        n = s.normals @ T[:3, :3].T
        facing = np.einsum("md,md->m", n, p) < 0  # normal points back towards the camera centre
        p = p[facing & (p[:, 2] > 1e-3)]
        u = np.round(p[:, 0] / p[:, 2] * cam.K[0, 0] + cam.K[0, 2]).astype(int)
        v = np.round(p[:, 1] / p[:, 2] * cam.K[1, 1] + cam.K[1, 2]).astype(int)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        out.append((v[inside], u[inside], p[inside, 2]))
    return out


def seen_counts(problem: Problem, scene: np.ndarray, samples: list[ModelSamples]) -> tuple[np.ndarray, np.ndarray]:
    """Per object of ``scene`` (K, 4, 4), its camera-facing surface samples that the sensor sees through (observed
    depth well behind the surface) and that it sees on the surface -> (through (K,), on (K,)) counts. The rest lie
    behind what the sensor sees (hidden) or have no reading."""
    obs = problem.observed
    through, on = np.zeros(len(samples), dtype=int), np.zeros(len(samples), dtype=int)
    for k, (v, u, d) in enumerate(project_samples(problem, scene, samples)):
        o = obs[v, u]
        seen = o > 0
        through[k] = int((seen & (o > d + SEEN_THROUGH)).sum())
        on[k] = int((seen & (np.abs(o - d) < EXPLAINED)).sum())
    return through, on


def badness(through: np.ndarray, on: np.ndarray) -> np.ndarray:
    """Per object, the share of its camera-facing surface samples seen ``through`` among those seen through or
    ``on`` it (``seen_counts``, (K,) each) -> (K,) in [0, 1]; 1 for an object the sensor sees none of (out of view,
    or hidden: both counts 0)."""
    total = through + on
    return np.where(total > 0, through / np.maximum(total, 1), 1.0)


def unseen(through: np.ndarray, on: np.ndarray) -> np.ndarray:
    """(K,) bool: the objects of which the sensor sees no camera-facing surface sample, on the surface or through
    it (``seen_counts`` (K,) each, both 0): hidden behind what it sees, or out of view."""
    return through + on == 0


def object_badness(problem: Problem, scene: np.ndarray, samples: list[ModelSamples]) -> np.ndarray:
    """How badly each object of ``scene`` (K, 4, 4) explains its part of the observation -> (K,) in [0, 1]
    (``badness`` of its ``seen_counts``)."""
    return badness(*seen_counts(problem, scene, samples))


def _splat(problem: Problem, scene: np.ndarray, samples: list[ModelSamples], objects: list[int]) -> np.ndarray:
    """The nearest depth (h, w) m of the ``objects`` of ``scene`` (K, 4, 4) on the problem grid, each surface
    sample splatted over its 3x3 neighbourhood (samples are sparser than pixels); inf where none is."""
    h, w = problem.observed.shape
    zbuf = np.full((h, w), np.inf)
    projected = project_samples(problem, scene[objects], [samples[k] for k in objects])
    for v, u, d in projected:
        for dv in (-1, 0, 1):
            for du in (-1, 0, 1):
                vv, uu = np.clip(v + dv, 0, h - 1), np.clip(u + du, 0, w - 1)
                np.minimum.at(zbuf, (vv, uu), d)
    return zbuf


def unclaimed(problem: Problem, scene: np.ndarray, samples: list[ModelSamples], k: int) -> np.ndarray:
    """The observed depth (h, w) m with the pixels that the objects of ``scene`` (K, 4, 4) other than ``k``
    explain (their surface within EXPLAINED of the reading) set to 0, no reading: what is left for object k."""
    others = [j for j in range(len(scene)) if j != k]
    obs = problem.observed
    return np.where(np.abs(obs - _splat(problem, scene, samples, others)) < EXPLAINED, 0.0, obs)


def unexplained(problem: Problem, points: ScenePoints, scene: np.ndarray | None,
                samples: list[ModelSamples]) -> np.ndarray:
    """(P,) bool: the observed points above the table that no object of ``scene`` (K, 4, 4) covers at about their
    depth (all of them when ``scene`` is None)."""
    if scene is None:
        return np.ones(len(points.points), dtype=bool)
    zbuf = _splat(problem, scene, samples, list(range(len(scene))))
    r, c = points.pixels[:, 0], points.pixels[:, 1]
    return ~(np.abs(problem.observed[r, c] - zbuf[r, c]) < EXPLAINED)


def clusters(points: np.ndarray, voxel: float = 0.01, min_points: int = 8) -> list[np.ndarray]:
    """Groups of nearby points (P, 3) -> list of (P_i, 3) arrays, largest first: connected components of the
    occupied cells of a ``voxel`` grid (26-connected, so points up to about two voxels apart join). Deterministic
    and fast; groups of fewer than ``min_points`` points are dropped."""
    if len(points) < min_points:
        return []
    cell = np.floor((points - points.min(axis=0)) / voxel).astype(int)
    grid = np.zeros(cell.max(axis=0) + 1, dtype=bool)
    grid[tuple(cell.T)] = True
    labels, n = ndimage.label(grid, structure=np.ones((3, 3, 3)))
    of_point = labels[tuple(cell.T)]
    groups = [points[of_point == i] for i in range(1, n + 1)]
    return sorted([g for g in groups if len(g) >= min_points], key=len, reverse=True)
