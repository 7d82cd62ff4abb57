"""The support surface: the table frame of a depth frame, the table's extent and where the objects stand.

With no extrinsics the table is the dominant plane under the objects: several RANSAC planes are fitted to a
subsampled cloud, walls and monitors are rejected because their normals point down in the image (the camera is
roughly upright), and of the planes that face up the one covering most of the image centre wins (the floor and
box tops cover less of it than the table the objects stand on). The winner is refit by weighted least squares with
a sensor noise model, so that far, noisy points count less.

Table frame: z = plane normal towards the camera; origin = the object region's centre on the plane; x = the
camera's x axis projected onto the plane.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from workbench.errors import InputError
from workbench.geometry import invert_pose, make_pose, transform_points
from workbench.problem.scene import Camera, Frame, Table

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SupportConfig:
    """Settings of ``estimate_support``; lengths in metres."""

    max_points: int = 30000  # the depth image is subsampled on a regular grid to about this many points
    max_planes: int = 6  # RANSAC planes extracted, largest first
    min_plane_fraction: float = 0.03  # smaller planes (share of the valid points) are not support candidates
    ransac_threshold: float = 0.01  # at least this; raised to 2.5 sigma of the sensor noise at the median depth
    ransac_iterations: int = 1000
    max_up_y: float = 0.2  # a support normal's camera-y component is below this (camera roughly upright)
    refine_sigmas: float = 3.0  # table points lie within this many noise sigmas of the plane, or within:
    min_height: float = 0.005  # higher points are above the table
    max_height: float = 0.40  # clusters of points above the table that reach higher are walls, monitors, people
    edge_margin: float = 0.03  # object points lie this far inside the table's outline
    min_object_height: float = 0.015  # a cluster whose top is lower is table unevenness, not an object
    cluster_voxel: float = 0.01  # the points above the table are clustered on this voxel grid
    cluster_eps: float = 0.025  # DBSCAN neighbourhood
    extent_percentiles: tuple[float, float] = (1.0, 99.0)  # of the table inliers, against stray points
    # Where the table runs out of the image its edge is unseen: that side of the extent is pushed out this far, so
    # that physics does not drop objects near the image border off an edge that is only the field of view's.
    unseen_extension: float = 0.3
    border_near: float = 0.03  # a side is judged by what is seen this far beyond it
    unseen_share: float = 0.5  # of that line out of the image or on the table plane: the table may go on there
    # A raised support (a large box's top, a shelf) parallel to the table and at least this big each way (larger
    # than a handheld object's face) becomes the support when more of what stands stands on it than on the table.
    raised_min_size: float = 0.2
    raised_min_height: float = 0.03  # lower "planes" above the table are the table itself, unevenly fitted
    raised_max_tilt_deg: float = 5.0
    raised_planes: int = 3  # planes tried among the points above the table, largest first
    # ... and it holds the objects: the volume seen above it (each cell filled from the top up to what is seen, so
    # hidden far sides are missing) is at least this share of theirs (0.38-0.68 on generated raised boxes; a box
    # with another stacked on it, unmodelled clutter as high beside it: 0.15).
    raised_holds: float = 0.25
    # A cluster above max_height is a stack of the frame's objects, not a wall or a monitor, when its top is within
    # what they reach stacked and the volume seen in it is at most this share of theirs (1.0-1.1 on the two
    # generated stacks 41 cm high; no wall or monitor in the shared sets reaches 40 cm, so none was measured).
    stack_holds: float = 1.5
    seed: int = 0


def depth_noise_sigma(z: np.ndarray) -> np.ndarray:
    """Axial noise (metres) of a structured-light sensor at depth ``z`` (metres), (...) -> (...).

    Kinect v1 model of Nguyen, Izadi and Lovell (2012); Xtion and PrimeSense sensors are alike, and for
    time-of-flight sensors and renderers it is merely conservative."""
    return 0.0012 + 0.0019 * (np.asarray(z) - 0.4) ** 2


def _grid_points(depth: np.ndarray, K: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Valid pixels of a regular subsampling grid -> camera-frame points (N, 3) and their pixels (N, 2) (u, v)."""
    n_valid = int(np.count_nonzero(depth > 0))
    stride = max(1, int(np.ceil(np.sqrt(n_valid / max_points))))
    v, u = np.mgrid[0 : depth.shape[0] : stride, 0 : depth.shape[1] : stride]
    z = depth[v, u].astype(np.float64)
    ok = z > 0
    u, v, z = u[ok], v[ok], z[ok]
    # OpenCV convention: pixel (u, v) is centred on the integer coordinates K maps to.
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], axis=-1), np.stack([u, v], axis=-1)


def _ransac_planes(points: np.ndarray, cfg: SupportConfig) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """Largest planes first: (normal (3,) towards the camera, offset d > 0 with n.p + d = 0, inlier indices)."""
    threshold = max(cfg.ransac_threshold, 2.5 * float(depth_noise_sigma(np.median(points[:, 2]))))
    rng = np.random.default_rng(cfg.seed)
    remaining = np.arange(len(points))
    planes = []
    min_inliers = max(3, int(cfg.min_plane_fraction * len(points)))
    for _ in range(cfg.max_planes):
        if len(remaining) < min_inliers:
            break
        n, d = ransac_plane(points[remaining], threshold, cfg.ransac_iterations, rng)
        idx = np.flatnonzero(np.abs(points[remaining] @ n + d) < threshold)
        if len(idx) < min_inliers:
            break
        if d < 0:  # the camera (origin) must be on the positive side
            n, d = -n, -d
        planes.append((n, d, remaining[idx]))
        remaining = np.delete(remaining, idx)
    return planes


def ransac_plane(points: np.ndarray, threshold: float, iterations: int, rng: np.random.Generator,
                 chunk: int = 64, max_scored: int = 30000) -> tuple[np.ndarray, float]:
    """The plane (unit normal (3,), offset d with n.p + d = 0) through three of the ``points`` (N, 3) with the
    most points within ``threshold`` (m), of ``iterations`` random triples; counted on at most ``max_scored``
    evenly spread points. Plain numpy with the caller's generator: open3d's multi-threaded RANSAC gave a different
    table on every run, so no seeded run on a frame without a table pose could be repeated."""
    best, best_count = (np.array([0.0, 0.0, 1.0]), 0.0), -1
    scored = points[np.linspace(0, len(points) - 1, max_scored).astype(int)] if len(points) > max_scored else points
    for start in range(0, iterations, chunk):
        m = min(chunk, iterations - start)
        tri = points[rng.integers(0, len(points), size=(m, 3))]  # (m, 3, 3)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1)
        ok = norm > 1e-12  # degenerate (collinear) triples propose nothing
        n = n[ok] / norm[ok, None]
        d = -np.einsum("md,md->m", n, tri[ok, 0])
        if not len(n):
            continue
        counts = (np.abs(scored @ n.T + d) < threshold).sum(axis=0)
        i = int(np.argmax(counts))
        if counts[i] > best_count:
            best, best_count = (n[i], float(d[i])), int(counts[i])
    return best


def _central_weight(pix: np.ndarray, camera: Camera) -> np.ndarray:
    """1 at the image centre falling to 0 at the inscribed ellipse. (N, 2) -> (N,)."""
    r2 = ((pix[:, 0] - camera.width / 2) / (camera.width / 2)) ** 2
    r2 += ((pix[:, 1] - camera.height / 2) / (camera.height / 2)) ** 2
    return np.clip(1.0 - r2, 0.0, None)


def _choose_support(planes, pix: np.ndarray, camera: Camera, cfg: SupportConfig) -> int:
    """Index of the support plane among ``planes``: facing up, covering most of the image centre."""
    scores = np.array([_central_weight(pix[idx], camera).sum() for _, _, idx in planes])
    up = np.array([n[1] < cfg.max_up_y for n, _, _ in planes])
    if not up.any():
        log.warning("no plane faces up in the image (is the camera upside down?); taking the most central plane")
        up[:] = True
    return int(np.argmax(np.where(up, scores, -1.0)))


def _refine_plane(points: np.ndarray, n: np.ndarray, d: float, cfg: SupportConfig) -> tuple[np.ndarray, float]:
    """Weighted least-squares refit on the points near the plane, weights 1/sigma(z)^2. (N, 3) -> (n, d)."""
    sigma = depth_noise_sigma(points[:, 2])
    for widen in (2.0, 1.0, 1.0):  # RANSAC's plane is only roughly right: start wide
        near = np.abs(points @ n + d) < widen * cfg.refine_sigmas * sigma
        if near.sum() < 3:
            break
        p, w = points[near], 1.0 / sigma[near] ** 2
        c = (w[:, None] * p).sum(0) / w.sum()
        cov = ((p - c) * w[:, None]).T @ (p - c)
        n_new = np.linalg.eigh(cov)[1][:, 0]
        n = n_new if n_new @ n > 0 else -n_new
        d = float(-n @ c)
    return n, d


def _plane_frame(n: np.ndarray, d: float) -> np.ndarray:
    """T_cam_world of a frame with z = n, origin at the camera's foot on the plane, x = camera x projected."""
    x = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(x) < 0.1:  # camera x nearly along the normal (camera rolled 90 degrees onto its side)
        x = np.array([0.0, 1.0, 0.0]) - n[1] * n
    x /= np.linalg.norm(x)
    return make_pose(np.stack([x, np.cross(n, x), n], axis=-1), -d * n)


def _noise_band(z_cam: np.ndarray, cfg: SupportConfig) -> np.ndarray:
    """How far (m) a reading at camera depth ``z_cam`` (N,) may lie from the plane and still be the plane -> (N,)."""
    return np.maximum(cfg.min_height, cfg.refine_sigmas * depth_noise_sigma(z_cam))


def _on_table(world: np.ndarray, z_cam: np.ndarray, cfg: SupportConfig) -> np.ndarray:
    """Which points (N, 3) in the table frame lie on z = 0, within sensor noise. ``z_cam``: (N,) -> mask (N,)."""
    return np.abs(world[:, 2]) < _noise_band(z_cam, cfg)


def _cross_2d(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _convex_hull_2d(p: np.ndarray, resolution: float) -> np.ndarray:
    """Counter-clockwise hull vertices (V, 2) of points (N, 2) (Andrew's monotone chain), to ``resolution``."""
    # Only the lowest and highest point of each column of width ``resolution`` can be a vertex (to within it):
    # this keeps the Python loop below short.
    p = p[np.lexsort((p[:, 1], np.floor(p[:, 0] / resolution)))]
    first = np.unique(np.floor(p[:, 0] / resolution), return_index=True)[1]
    p = np.unique(p[np.r_[first, first[1:] - 1, len(p) - 1]], axis=0)
    if len(p) < 3:
        return p

    def half(points):
        chain = []
        for q in points:
            while len(chain) >= 2 and _cross_2d(chain[-1] - chain[-2], q - chain[-2]) <= 0:
                chain.pop()
            chain.append(q)
        return chain[:-1]

    return np.array(half(p) + half(p[::-1]))


def _inside_hull(p: np.ndarray, hull: np.ndarray, margin: float) -> np.ndarray:
    """Which points (N, 2) lie at least ``margin`` inside the counter-clockwise convex polygon (V, 2) -> (N,)."""
    edges = np.roll(hull, -1, axis=0) - hull
    outward = np.stack([edges[:, 1], -edges[:, 0]], axis=-1) / np.linalg.norm(edges, axis=-1, keepdims=True)
    return np.all(np.einsum("nvk,vk->nv", p[:, None, :] - hull[None], outward) <= -margin, axis=1)


def _table_outline(
    on_table: np.ndarray, cfg: SupportConfig, path
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Convex outline (V, 2) and robust extent (x_min, x_max, y_min, y_max) of the table, from its points (M, 3).

    Only the large connected pieces count: coplanar bits elsewhere (another desk, a shelf) would inflate both."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(on_table)).voxel_down_sample(cfg.cluster_voxel)
    pts = np.asarray(cloud.points)[:, :2]  # voxels weigh area evenly, unlike pixels that crowd near the camera
    labels = np.asarray(cloud.cluster_dbscan(cfg.cluster_eps, min_points=5))
    sizes = np.bincount(labels[labels >= 0]) if np.any(labels >= 0) else np.zeros(0, dtype=int)
    if len(sizes) == 0:
        raise InputError(path, "the table plane has too few points in the depth image")
    # Objects may cut the visible table in pieces: keep every large one.
    pts = pts[np.isin(labels, np.flatnonzero(sizes >= 0.2 * sizes.max()))]
    hull = _convex_hull_2d(pts, cfg.cluster_voxel)
    if len(hull) < 3:
        raise InputError(path, "the table plane's points in the depth image lie on a line")
    lo, hi = np.percentile(pts, cfg.extent_percentiles, axis=0)
    return hull, (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))


def _extend_unseen_sides(
    extent: tuple[float, float, float, float], depth: np.ndarray, camera: Camera, T_cam_world: np.ndarray,
    cfg: SupportConfig,
) -> tuple[float, float, float, float]:
    """Push each side of ``extent`` (x_min, x_max, y_min, y_max; m, in the table frame of ``T_cam_world``) out by
    ``cfg.unseen_extension`` where the table may go on: where most of a line ``cfg.border_near`` beyond the side
    lies out of the image, or on pixels whose depth (H, W; m) is the table plane's. A side whose beyond is seen as
    something else (the floor far below, a wall, no return) is a real edge and stays."""
    x_min, x_max, y_min, y_max = extent
    t = np.linspace(0.0, 1.0, 41)
    d = cfg.border_near
    lines = {  # side -> (41, 3) points just beyond it
        "x_min": np.stack([np.full_like(t, x_min - d), y_min + t * (y_max - y_min), 0 * t], -1),
        "x_max": np.stack([np.full_like(t, x_max + d), y_min + t * (y_max - y_min), 0 * t], -1),
        "y_min": np.stack([x_min + t * (x_max - x_min), np.full_like(t, y_min - d), 0 * t], -1),
        "y_max": np.stack([x_min + t * (x_max - x_min), np.full_like(t, y_max + d), 0 * t], -1),
    }
    H, W = depth.shape
    out = dict(x_min=x_min, x_max=x_max, y_min=y_min, y_max=y_max)
    for side, pts in lines.items():
        cam = transform_points(T_cam_world, pts)
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(camera.K[0, 0] * cam[:, 0] / z + camera.K[0, 2])
            v = np.round(camera.K[1, 1] * cam[:, 1] / z + camera.K[1, 2])
        inside = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        seen = depth[v[inside].astype(int), u[inside].astype(int)]
        table = np.abs(seen - z[inside]) < _noise_band(z[inside], cfg)
        if (np.count_nonzero(~inside) + np.count_nonzero(table)) / len(t) >= cfg.unseen_share:
            out[side] += cfg.unseen_extension if side.endswith("max") else -cfg.unseen_extension
    return out["x_min"], out["x_max"], out["y_min"], out["y_max"]


def _column_volume(points: np.ndarray, base: float, voxel: float) -> float:
    """Volume (m^3) under points (N, 3) down to the height ``base`` (m): each ``voxel`` cell filled from its highest
    point down (hidden far sides are missing, overhangs filled)."""
    cells = {}
    for (x, y), z in zip(np.round(points[:, :2] / voxel).astype(int).tolist(), points[:, 2] - base):
        cells[x, y] = max(cells.get((x, y), 0.0), z)
    return sum(cells.values()) * voxel ** 2


def _object_region(
    world: np.ndarray, z_cam: np.ndarray, outline: np.ndarray, cfg: SupportConfig, path,
    objects_volume: float | None = None, objects_reach: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """xy bounding box (min (2,), max (2,)) of the object clusters standing on the table. Clutter on the table that
    the image border cuts below ``max_height`` (a monitor's lower half, say) stays in: nothing tells it apart.
    A taller cluster stays in when the objects (``objects_volume``, m^3; ``objects_reach``, m: the sum of their
    largest sizes) could be it, stacked (``stack_holds``).

    ``world``: (N, 3) points in the table frame; ``z_cam``: (N,) their depths (noise model); ``outline``: (V, 2)."""
    above = world[:, 2] > _noise_band(z_cam, cfg)
    # The margin drops the foot of a wall behind the desk, which noise spreads over the table's far edge.
    above[above] = _inside_hull(world[above, :2], outline, cfg.edge_margin)
    if not above.any():
        raise InputError(path, "nothing stands on the table: no depth point lies above the support plane")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world[above])).voxel_down_sample(cfg.cluster_voxel)
    pts = np.asarray(cloud.points)
    labels = np.asarray(cloud.cluster_dbscan(cfg.cluster_eps, min_points=5))
    keep, tall = np.zeros(len(pts), dtype=bool), np.zeros(len(pts), dtype=bool)
    for label in range(labels.max() + 1):
        member = labels == label
        top = pts[member, 2].max()
        if cfg.min_object_height <= top <= cfg.max_height:
            keep |= member
        elif top > cfg.max_height:
            if _a_stack(pts[member], objects_volume, objects_reach, cfg):
                keep |= member
            else:
                tall |= member
    if not keep.any() and tall.any():
        # Only clusters taller than max_height (which drops walls and monitors): a stack of tall boxes is one, and
        # no object region at all would end the run, so they are the region.
        log.warning("%s: nothing stands on the table up to %g cm; taking what stands up to %.0f cm as the objects",
                    path, cfg.max_height * 100, pts[tall, 2].max() * 100)
        keep = tall
    if not keep.any():
        raise InputError(
            path, f"nothing stands on the table: no cluster of points {cfg.min_object_height * 100:g}-"
            f"{cfg.max_height * 100:g} cm above the support plane"
        )
    half = cfg.cluster_voxel / 2  # voxel centres sit up to half a voxel inside the surface
    return pts[keep, :2].min(0) - half, pts[keep, :2].max(0) + half


def _a_stack(cluster: np.ndarray, objects_volume: float | None, objects_reach: float | None,
             cfg: SupportConfig) -> bool:
    """Whether a cluster (N, 3) taller than ``max_height`` can be the objects stacked (see ``stack_holds``)."""
    if objects_volume is None or objects_reach is None or cluster[:, 2].max() > objects_reach:
        return False
    return _column_volume(cluster, 0.0, cfg.cluster_voxel) <= cfg.stack_holds * objects_volume


def _raised_support(world: np.ndarray, z_cam: np.ndarray, outline: np.ndarray, cfg: SupportConfig,
                    objects_volume: float | None = None) -> float | None:
    """The height (m) above the table of a raised support the objects stand on, or None. ``world``: (N, 3) points
    in the table frame, ``z_cam`` (N,) their depths, ``outline`` (V, 2) the table's.

    A raised support is a plane among the points above the table, parallel to it (``raised_max_tilt_deg``), at
    least ``raised_min_height`` above it, whose largest connected piece is at least ``raised_min_size`` across both
    ways and fills at least half of its outline (a box's top, not the tops of several objects at one height), with
    more of what stands above the table (voxels ``min_object_height`` or more above it) standing on it, within its
    outline, than standing on the table beside it; and, where the objects' ``objects_volume`` (m^3, all of them) is
    given, at least ``raised_holds`` of it seen above the top (each cell filled from the top up to what is seen):
    a box with a small one stacked on it, next to unmodelled clutter as high, is a base object, not a support.
    A frame of objects on a large box: the physics of the table
    alone would drop them through the box, unmodelled, onto the table, where no hypothesis matches the depth.
    Objects on both the table and the box keep the table (the box's objects are then lost: one support per
    frame)."""
    band = _noise_band(z_cam, cfg)
    above = (world[:, 2] > band) & (world[:, 2] < cfg.max_height)
    above[above] = _inside_hull(world[above, :2], outline, cfg.edge_margin)
    if above.sum() < 100:
        return None
    pts, zc = world[above], z_cam[above]
    threshold = max(cfg.ransac_threshold, 2.5 * float(depth_noise_sigma(np.median(zc))))
    voxel = cfg.cluster_voxel
    voxels = (np.unique(np.floor(pts / voxel).astype(int), axis=0) + 0.5) * voxel
    standing = voxels[voxels[:, 2] > cfg.min_object_height]
    rng = np.random.default_rng(cfg.seed)
    remaining = np.arange(len(pts))
    best = None
    for _ in range(cfg.raised_planes):
        if len(remaining) < 100:
            break
        n, d = ransac_plane(pts[remaining], threshold, cfg.ransac_iterations, rng)
        inliers = remaining[np.abs(pts[remaining] @ n + d) < threshold]
        remaining = np.setdiff1d(remaining, inliers)
        height = float(np.median(pts[inliers, 2])) if len(inliers) else 0.0
        if abs(n[2]) < np.cos(np.radians(cfg.raised_max_tilt_deg)) or height < cfg.raised_min_height:
            continue
        top = _largest_piece(pts[inliers, :2], cfg)
        if top is None:
            continue
        piece, hull = top
        size = piece.max(axis=0) - piece.min(axis=0)
        if size.min() < cfg.raised_min_size or len(piece) * voxel ** 2 < 0.5 * _polygon_area(hull):
            continue
        beside = ~_inside_hull(standing[:, :2], hull, -cfg.edge_margin)  # the top's own sides stand within it
        on_top = _inside_hull(standing[:, :2], hull, 0.0) & (standing[:, 2] > height + cfg.min_object_height)
        volume = _column_volume(standing[on_top], height, voxel)
        holds = objects_volume is None or volume >= cfg.raised_holds * objects_volume
        log.debug("raised plane %.3f m: %d voxels on it, %d beside, %.0f cm^3 above it", height, on_top.sum(),
                  beside.sum(), volume * 1e6)
        if on_top.sum() > beside.sum() and holds and (best is None or height > best):
            best = height
    return best


def _largest_piece(xy: np.ndarray, cfg: SupportConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """The largest connected piece of points (N, 2) on a ``cluster_voxel`` grid -> (its voxel centres (M, 2), their
    convex hull (V, 2)), or None when there is none of at least 3 voxels."""
    cells = np.unique(np.floor(xy / cfg.cluster_voxel).astype(int), axis=0)
    if len(cells) < 3:
        return None
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.c_[cells * cfg.cluster_voxel, np.zeros(len(cells))]))
    labels = np.asarray(cloud.cluster_dbscan(cfg.cluster_eps, min_points=3))
    if not np.any(labels >= 0):
        return None
    piece = (cells[labels == np.argmax(np.bincount(labels[labels >= 0]))] + 0.5) * cfg.cluster_voxel
    hull = _convex_hull_2d(piece, cfg.cluster_voxel)
    return (piece, hull) if len(hull) >= 3 else None


def _polygon_area(p: np.ndarray) -> float:
    """Area (m^2) of a simple polygon (V, 2)."""
    return 0.5 * abs(float(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(p[:, 1], np.roll(p[:, 0], -1))))


def _given_frame_fits(T_cam_world: np.ndarray, points: np.ndarray, cfg: SupportConfig) -> bool:
    """Whether the given table frame looks like one: the camera above z = 0 and enough points on it."""
    T_world_cam = invert_pose(T_cam_world)
    on = _on_table(transform_points(T_world_cam, points), points[:, 2], cfg)
    return T_world_cam[2, 3] > 0 and on.mean() >= cfg.min_plane_fraction


def estimate_support(frame: Frame, cfg: SupportConfig = SupportConfig(), objects_volume: float | None = None,
                     objects_reach: float | None = None, raised: bool = True) -> tuple[Camera, Table]:
    """The camera with ``T_cam_world`` set and the ``Table`` (extent and object region) of ``frame``: the table, or
    a raised support the objects stand on (``_raised_support``; ``objects_volume``, m^3: the frame's objects'),
    with the objects' region keeping a stack taller than ``max_height`` that they could be (``objects_reach``, m:
    the sum of their largest sizes).

    A given ``frame.camera.T_cam_world`` is kept (only extent and region are measured) unless the depth
    contradicts it (camera below the table, almost no point on z = 0); then a warning is logged and the table is
    estimated from the depth. ``raised`` False: a given pose is the support itself, no raised one looked for above
    it (a sequence's next frame, whose table frame the frame before found). Raises ``InputError`` when there is no
    depth, no support plane or nothing on it."""
    camera, path = frame.camera, frame.source
    depth = np.asarray(frame.depth, dtype=np.float64)
    depth[~np.isfinite(depth)] = 0.0
    if not np.any(depth > 0):
        raise InputError(path, "depth image has no valid pixel")
    points, pix = _grid_points(depth, camera.K, cfg.max_points)

    T = camera.T_cam_world
    if T is not None and not _given_frame_fits(T, points, cfg):
        log.warning("%s: the given T_cam_world does not match the depth (no table at z = 0); estimating it", path)
        T = None
    estimated = T is None
    if estimated:
        planes = _ransac_planes(points, cfg)
        if not planes:
            raise InputError(path, "no planar support surface found in the depth image")
        n, d, _ = planes[_choose_support(planes, pix, camera, cfg)]
        T = _plane_frame(*_refine_plane(points, n, d, cfg))

    world = transform_points(invert_pose(T), points)
    outline, extent = _table_outline(world[_on_table(world, points[:, 2], cfg)], cfg, path)
    height = _raised_support(world, points[:, 2], outline, cfg, objects_volume) if raised or estimated else None
    if height is not None:  # the objects stand on a box or a shelf: its top is their support
        log.info("%s: the objects stand on a raised support %.0f cm above the table", path, height * 100)
        T = T @ make_pose(np.eye(3), np.array([0.0, 0.0, height]))
        world = transform_points(invert_pose(T), points)
        outline, extent = _table_outline(world[_on_table(world, points[:, 2], cfg)], cfg, path)
    extent = _extend_unseen_sides(extent, depth, camera, T, cfg)
    lo, hi = _object_region(world, points[:, 2], outline, cfg, path, objects_volume, objects_reach)
    if estimated:
        # Put the origin at the centre of the objects: where the estimator's attention is.
        c = (lo + hi) / 2
        T = T @ make_pose(np.eye(3), np.array([c[0], c[1], 0.0]))
        extent = (extent[0] - c[0], extent[1] - c[0], extent[2] - c[1], extent[3] - c[1])
        lo, hi = lo - c, hi - c
    table = Table(*map(float, extent), region_min=(float(lo[0]), float(lo[1])), region_max=(float(hi[0]), float(hi[1])))
    return camera.with_pose(T), table
