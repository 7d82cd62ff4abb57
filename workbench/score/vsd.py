"""BOP's Visible Surface Discrepancy (VSD), as the BOP toolkit defines it (``bop_toolkit_lib/pose_error.py``
``vsd`` with ``visibility.py``'s "bop19" visibility masks and the "step" pixel cost).

VSD compares only what the camera sees: the object is rendered alone at the estimated and at the true pose, at the
frame's full resolution, and each rendering is masked to the pixels where it is not behind the observed depth by
more than ``delta`` (pixels without a depth reading count as visible). Over the union of the two masks, a pixel is
an error when only one mask holds it or when the two renderings differ there by ``tau`` or more:

    e_VSD = (#{p in V_gt & V_est : |D_gt(p) - D_est(p)| >= tau} + #(V_gt xor V_est)) / #(V_gt | V_est)

(1 when the union is empty). So a mug whose handle is hidden is not wrong for the handle's place, while an object
in the wrong place is. The distances D are along each pixel's ray (distance images), as the toolkit compares them.

Two readings (BOP's): the classic one, ``tau`` 20 mm, an object VSD-right when e_VSD < ``theta`` 0.3; and the BOP
2019 average recall AR_VSD, the share of the (tau, theta) pairs, tau in 0.05..0.5 of the object's diameter and
theta in 0.05..0.5 (steps of 0.05), under which e_VSD < theta: per object here, averaged over objects by the caller.

Units: metres throughout (BOP files hold mm: tau 20 mm = 0.020 here); depth is camera z, 0 where there is none.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial.distance import pdist

_STEPS = tuple(round(0.05 * k, 2) for k in range(1, 11))  # 0.05, 0.10, ..., 0.50


@dataclass(frozen=True)
class VSDConfig:
    """``delta``: metres, the visibility tolerance (BOP: 15 mm for every dataset). ``tau``: metres, the classic
    misalignment tolerance; ``theta``: the classic correctness threshold. ``ar_taus``: tolerances of AR_VSD as
    fractions of the object's diameter; ``ar_thetas``: its correctness thresholds."""

    delta: float = 0.015
    tau: float = 0.020
    theta: float = 0.3
    ar_taus: tuple[float, ...] = _STEPS
    ar_thetas: tuple[float, ...] = _STEPS


@dataclass(frozen=True)
class ObjectVSD:
    """One object's VSD: ``error`` e_VSD at ``VSDConfig.tau``, in [0, 1]; ``right`` error < theta; ``ar`` the
    share of AR_VSD's (tau, theta) pairs under which it is right, in [0, 1]."""

    error: float
    right: bool
    ar: float


# An object with no estimate (or nothing to compare): every pixel an error, as BOP counts a missed instance.
MISSED = ObjectVSD(1.0, False, 0.0)


def distance_image(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-z depth (H, W) metres -> distance from the camera centre along each pixel's ray (H, W) float64 metres,
    0 where the depth is 0. Pixel (u, v) is image point (u, v) of ``K`` (OpenCV: integer coordinates at pixel
    centres), as the toolkit's ``depth_im_to_dist_im_fast``."""
    depth = np.asarray(depth, dtype=np.float64)
    h, w = depth.shape
    x = (np.arange(w) - K[0, 2]) / K[0, 0]
    y = (np.arange(h) - K[1, 2]) / K[1, 1]
    return depth * np.sqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2)


def visibility_masks(dist_test: np.ndarray, dist_gt: np.ndarray, dist_est: np.ndarray, delta: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The visible surface of the object at the true and at the estimated pose: (V_gt, V_est), each (H, W) bool.
    Inputs (H, W) distance images, metres, 0 = nothing there; ``delta`` metres.

    A rendered pixel is visible where it lies at most ``delta`` behind the observation, or where the sensor saw
    nothing (BOP 2019: shiny and dark objects often lose their depth). The estimate's mask also holds the pixels of
    V_gt it covers: where the true object is seen, an estimate there is seen too even if the observation says it
    would be hidden (Hodan et al. 2016, eq. 14)."""
    seen_or_missing = dist_test == 0

    def visible(dist_model: np.ndarray) -> np.ndarray:
        return ((dist_model - dist_test <= delta) | seen_or_missing) & (dist_model > 0)

    visib_gt = visible(dist_gt)
    visib_est = visible(dist_est) | (visib_gt & (dist_est > 0))
    return visib_gt, visib_est


def vsd_errors(dist_test: np.ndarray, dist_gt: np.ndarray, dist_est: np.ndarray, taus: np.ndarray,
               delta: float) -> np.ndarray:
    """e_VSD with the step cost for each misalignment tolerance. Distance images (H, W) metres (``distance_image``),
    ``taus`` (T,) metres, ``delta`` metres -> (T,) errors in [0, 1]; all 1 when neither pose shows a visible
    pixel."""
    taus = np.atleast_1d(np.asarray(taus, dtype=np.float64))
    visib_gt, visib_est = visibility_masks(dist_test, dist_gt, dist_est, delta)
    both = visib_gt & visib_est
    union = int((visib_gt | visib_est).sum())
    if union == 0:
        return np.ones(len(taus))
    only_one = union - int(both.sum())
    dists = np.abs(dist_gt[both] - dist_est[both])
    return np.array([(np.count_nonzero(dists >= tau) + only_one) / union for tau in taus])


def object_vsd(dist_test: np.ndarray, dist_gt: np.ndarray, dist_est: np.ndarray, diameter: float,
               config: VSDConfig = VSDConfig()) -> ObjectVSD:
    """The classic e_VSD and the object's share of AR_VSD. Distance images (H, W) metres; ``diameter`` metres (the
    object's largest extent: AR_VSD's tolerances are fractions of it)."""
    taus = np.concatenate([[config.tau], np.asarray(config.ar_taus) * diameter])
    errors = vsd_errors(dist_test, dist_gt, dist_est, taus, config.delta)
    # BOP counts a match correct when its error is strictly below the threshold.
    hits = errors[1:, None] < np.asarray(config.ar_thetas)[None, :]
    return ObjectVSD(float(errors[0]), bool(errors[0] < config.theta), float(hits.mean()))


def diameter(mesh: trimesh.Trimesh) -> float:
    """The largest distance between two points of the mesh (metres), as the BOP toolkit's ``calc_model_info``
    computes models_info's ``diameter``: found among the convex hull's vertices. Computed rather than read, since
    some datasets' models_info holds another number there (ycbv-real-dev's: the bounding box's diagonal)."""
    vertices = np.asarray(mesh.convex_hull.vertices if len(mesh.vertices) > 3 else mesh.vertices)
    return float(pdist(vertices).max()) if len(vertices) > 1 else 0.0


# Where an object not being drawn is put: far behind the camera, where every triangle is clipped away.
_BEHIND = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, -1e3], [0, 0, 0, 1.0]])


def render_alone(K: np.ndarray, width: int, height: int, meshes: list[trimesh.Trimesh],
                 poses: list[tuple[int, np.ndarray]]) -> np.ndarray:
    """Each ``(mesh index, T_cam_obj (4, 4) metres)`` of ``poses`` drawn alone, the full mesh, at ``width`` x
    ``height`` with intrinsics ``K`` -> (N, H, W) float32 camera-z depth in metres, 0 where the object is not.
    One renderer and one batch for all of them (the renderer's context costs more than a frame's renderings)."""
    from workbench.problem.scene import Camera
    from workbench.render.depth import DepthRenderer, RenderConfig

    out = np.zeros((len(poses), height, width), dtype=np.float32)
    if not poses:
        return out
    scenes = np.repeat(np.repeat(_BEHIND[None, None], len(meshes), axis=1), len(poses), axis=0)
    for n, (k, T) in enumerate(poses):
        scenes[n, k] = T
    # The camera frame serves as the renderer's world frame; the full meshes, as the toolkit draws its models.
    config = RenderConfig(max_framebuffer=max(2048, width, height), max_depth_error=0.0)
    with DepthRenderer(Camera(np.asarray(K, dtype=np.float64), width, height, np.eye(4)), meshes, config) as r:
        return r.render(scenes)


def frame_vsd(depth: np.ndarray, K: np.ndarray, meshes: list[trimesh.Trimesh], diameters: list[float],
              objects: list[tuple[int, np.ndarray, np.ndarray | None]], config: VSDConfig = VSDConfig()
              ) -> list[ObjectVSD]:
    """VSD of every object of one frame. ``depth`` (H, W) metres, the observation (0 = no reading); ``K`` (3, 3);
    ``meshes`` and ``diameters`` (metres) per model; ``objects``: (mesh index, T_gt, T_est or None), poses (4, 4)
    in the camera frame, metres. An object without an estimate, or without a finite true pose, is ``MISSED``."""
    h, w = depth.shape
    todo = [i for i, (_, T_gt, T_est) in enumerate(objects)
            if T_est is not None and np.isfinite(T_gt).all() and np.isfinite(T_est).all()]
    poses = [(objects[i][0], T) for i in todo for T in (objects[i][1], objects[i][2])]
    rendered = render_alone(K, w, h, meshes, poses)
    dist_test = distance_image(depth, K)
    out = [MISSED] * len(objects)
    for n, i in enumerate(todo):
        dist_gt, dist_est = (distance_image(rendered[2 * n + j], K) for j in (0, 1))
        out[i] = object_vsd(dist_test, dist_gt, dist_est, diameters[objects[i][0]], config)
    return out
