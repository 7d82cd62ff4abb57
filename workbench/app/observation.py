"""The static picture of a loaded frame, built in the engine process and sent to the server once per load:
the depth frame as a coloured point cloud, the depth image for the panel, the table, the meshes, the camera and
the problem grid onto which heatmaps are drawn."""

from __future__ import annotations

import numpy as np

from workbench.app.colors import VIRIDIS, apply_map, robust_range
from workbench.app.protocol import MeshData, ObservationView
from workbench.geometry import invert_pose, transform_points
from workbench.problem import Problem
from workbench.scene import Camera, Frame

MAX_CLOUD_POINTS = 60_000  # enough to read the scene, small enough to orbit smoothly in software WebGL
MAX_IMAGE_WIDTH = 320  # the panel is ~20 em wide


def backproject(camera: Camera, depth: np.ndarray, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Pixels with a reading -> (points (P, 3) in the camera frame, flat pixel indices (P,) into depth[::s, ::s]).

    Pixel (u, v) is the ray through image point (u, v) of K, as in the renderer."""
    d = depth[::stride, ::stride]
    v, u = np.nonzero(d > 0)
    z = d[v, u].astype(np.float64)
    K = camera.K
    x = (u * stride - K[0, 2]) / K[0, 0] * z
    y = (v * stride - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=-1), v * d.shape[1] + u


def height_colors(z: np.ndarray) -> tuple[np.ndarray, str]:
    """Colour by height above the table: the table itself grey, objects from viridis' dark (low) to yellow
    (high), points below the table darker grey."""
    top = max(0.05, float(np.percentile(z[z > 0.005], 99))) if np.any(z > 0.005) else 0.05
    colors = apply_map(z, 0.0, top, VIRIDIS)
    colors[np.abs(z) <= 0.005] = (150, 150, 150)
    colors[z < -0.005] = (90, 90, 90)
    return colors, f"height above the table, 0 (dark) to {top * 100:.0f} cm (yellow); table grey"


def depth_image(depth: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
    """(H, W) metres -> a coloured (H', W', 3) uint8 image no wider than MAX_IMAGE_WIDTH, and its depth range."""
    stride = max(1, int(np.ceil(depth.shape[1] / MAX_IMAGE_WIDTH)))
    d = depth[::stride, ::stride].astype(np.float64)
    lo, hi = robust_range(d[d > 0], 1.0, 99.0)
    return apply_map(np.where(d > 0, d, np.nan), lo, hi), (lo, hi)


def build_view(frame: Frame, problem: Problem, title: str) -> ObservationView:
    camera = problem.camera
    T_world_cam = invert_pose(camera.T_cam_world)
    stride = max(1, int(np.ceil(np.sqrt(np.count_nonzero(frame.depth) / MAX_CLOUD_POINTS))))
    p_cam, flat = backproject(camera, frame.depth, stride)
    points = transform_points(T_world_cam, p_cam)
    if frame.rgb is not None:
        colors = frame.rgb[::stride, ::stride].reshape(-1, 3)[flat].astype(np.uint8)
        legend = "the frame's colour image"
    else:
        colors, legend = height_colors(points[:, 2])

    grid_cam, _ = backproject(problem.render_camera, problem.observed)
    grid_points = transform_points(T_world_cam, grid_cam)
    image, drange = depth_image(frame.depth)

    gt = None
    if frame.gt_T_cam_obj is not None:
        gt = T_world_cam[None] @ frame.gt_T_cam_obj
    t = problem.table
    return ObservationView(
        title=title,
        points=points.astype(np.float32),
        colors=colors,
        color_legend=legend,
        depth_image=image,
        depth_range=drange,
        table=(t.x_min, t.x_max, t.y_min, t.y_max),
        region=(t.region_min[0], t.region_max[0], t.region_min[1], t.region_max[1]),
        meshes=[
            MeshData(m.name or f"obj_{m.obj_id}", np.asarray(m.mesh.vertices, np.float32), np.asarray(m.mesh.faces, np.int32))
            for m in problem.models
        ],
        T_world_cam=T_world_cam,
        K=np.asarray(camera.K, np.float64),
        image_size=(camera.width, camera.height),
        grid_points=grid_points.astype(np.float32),
        grid_mask=problem.observed > 0,
        gt_T_world_obj=gt,
    )
