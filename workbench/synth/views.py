"""The camera and what it sees: a camera drawn to show the scene, noise-free depth and object masks ray-cast with
open3d at full resolution (independent of the estimator's OpenGL renderer)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import trimesh

from workbench.geometry import invert_pose, make_pose
from workbench.synth.config import SynthConfig
from workbench.synth.distractors import Distractor
from workbench.synth.layout import Placed
from workbench.synth.objects import EZ, box_mesh, item_mesh


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """T_cam_world of an OpenCV camera at ``eye`` looking at ``target`` with the image's up roughly world z."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, EZ)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return invert_pose(make_pose(np.stack([x, y, z], axis=1), eye))


def pixel_rays(K: np.ndarray, width: int, height: int, window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Rays from the camera centre through pixel centres (integer u, v in K's convention), camera frame.

    Directions have z = 1, so a hit distance is the depth. ``window``: (x0, y0, x1, y1) exclusive end.
    -> (h, w, 6) float32."""
    x0, y0, x1, y1 = (0, 0, width, height) if window is None else window
    u, v = np.meshgrid(np.arange(x0, x1), np.arange(y0, y1))
    rays = np.zeros(u.shape + (6,), dtype=np.float32)
    rays[..., 3] = (u - K[0, 2]) / K[0, 0]
    rays[..., 4] = (v - K[1, 2]) / K[1, 1]
    rays[..., 5] = 1.0
    return rays


def raycast(meshes: list[trimesh.Trimesh], rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hits of rays (.., 6) among meshes (same frame as the rays).

    -> (depth (..) float32 in units of the ray direction's length, 0 = nothing; index (..) int32 of the mesh hit,
    -1 = nothing)."""
    scene = o3d.t.geometry.RaycastingScene()
    ids = []
    for m in meshes:
        tm = o3d.t.geometry.TriangleMesh()
        tm.vertex.positions = o3d.core.Tensor(np.asarray(m.vertices, dtype=np.float32))
        tm.triangle.indices = o3d.core.Tensor(np.asarray(m.faces, dtype=np.int32))
        ids.append(scene.add_triangles(tm))
    hit = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32)))
    t = hit["t_hit"].numpy()
    gid = hit["geometry_ids"].numpy().astype(np.int64)
    lookup = np.full(max(ids) + 2, -1, dtype=np.int32)
    lookup[ids] = np.arange(len(ids))
    index = np.where(np.isfinite(t), lookup[np.minimum(gid, len(lookup) - 1)], -1).astype(np.int32)
    return np.where(np.isfinite(t), t, 0.0).astype(np.float32), index


def project(K: np.ndarray, p_cam: np.ndarray) -> np.ndarray:
    """Pixel coordinates of camera-frame points. (N, 3) -> (N, 2)."""
    return (p_cam[:, :2] / p_cam[:, 2:3]) * np.diag(K)[:2] + K[:2, 2]


def _window(K, width, height, mesh_cam: trimesh.Trimesh) -> tuple[int, int, int, int] | None:
    """Pixel box (x0, y0, x1, y1) holding a camera-frame mesh's projection; None if it is not in front."""
    v = np.asarray(mesh_cam.vertices)
    if np.any(v[:, 2] <= 1e-3):
        return None
    uv = project(K, v)
    x0, y0 = np.floor(uv.min(axis=0)).astype(int) - 1
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 2
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    return None if x0 >= x1 or y0 >= y1 else (x0, y0, x1, y1)


def masks_alone(K, width, height, meshes_cam: list[trimesh.Trimesh]) -> np.ndarray:
    """Each object's silhouette as if it were alone in view. -> (K, H, W) bool."""
    out = np.zeros((len(meshes_cam), height, width), dtype=bool)
    for k, m in enumerate(meshes_cam):
        win = _window(K, width, height, m)
        if win is None:
            continue
        _, idx = raycast([m], pixel_rays(K, width, height, win))
        out[k, win[1]:win[3], win[0]:win[2]] = idx == 0
    return out


def visible_masks(K: np.ndarray, width: int, height: int, meshes: list[trimesh.Trimesh],
                  T_cam_obj: np.ndarray) -> np.ndarray:
    """Visible pixels of each object among the others (no table: it hides nothing resting on it).

    ``meshes``: K model meshes (metres); ``T_cam_obj``: (K, 4, 4). -> (K, H, W) bool."""
    posed = [m.copy().apply_transform(T) for m, T in zip(meshes, T_cam_obj)]
    _, idx = raycast(posed, pixel_rays(K, width, height))
    return idx[None] == np.arange(len(meshes))[:, None, None]


def support_meshes(cfg: SynthConfig) -> list[trimesh.Trimesh]:
    """The table (top at z = 0) and a floor far below, in the table frame."""
    table = box_mesh([*cfg.table_size, cfg.table_thickness]).apply_translation([0, 0, -cfg.table_thickness / 2])
    floor = box_mesh([20.0, 20.0, 0.01]).apply_translation([0, 0, cfg.floor_z - 0.005])
    return [table, floor]


def render_clean(cfg: SynthConfig, T_cam_world: np.ndarray, layout: list[Placed],
                 distractors: list[Distractor] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free depth of the table scene and which object each pixel shows.

    -> (depth (H, W) float32 metres, object index (H, W) int32: layout index, -1 for table, floor, distractors
    and nothing)."""
    world = support_meshes(cfg) + [item_mesh(p.item).apply_transform(p.T) for p in layout]
    world += [d.mesh().apply_transform(d.T) for d in distractors]
    cam = [m.apply_transform(T_cam_world) for m in world]
    depth, idx = raycast(cam, pixel_rays(cfg.K(), cfg.width, cfg.height))
    return depth, np.where((idx >= 2) & (idx < 2 + len(layout)), idx - 2, -1).astype(np.int32)


def draw_camera(cfg: SynthConfig, rng, layout: list[Placed], hide_normals: list[np.ndarray]) -> np.ndarray:
    """T_cam_world: 0.7-1.0 m from the table centre, 45-70 degrees up, looking at the boxes. With a hidden box the
    azimuth is drawn around the side opposite it, so that its tall partner stands in between."""
    if hide_normals:
        n = hide_normals[0]
        azimuth = np.arctan2(-n[1], -n[0]) + np.radians(rng.uniform(-1, 1) * cfg.hide_azimuth_jitter)
    else:
        azimuth = rng.uniform(-np.pi, np.pi)
    el = np.radians(rng.uniform(*cfg.cam_elevation))
    r = rng.uniform(*cfg.cam_distance)
    eye = r * np.array([np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth), np.sin(el)])
    target = np.mean([p.T[:3, 3] for p in layout], axis=0)
    return look_at(eye, target)


def draw_handle_camera(cfg: SynthConfig, rng, layout: list[Placed], hidden: bool) -> np.ndarray:
    """T_cam_world for the handle categories, ``layout[0]`` being the mug: with ``hidden``, low (15-35 degrees up)
    and on the far side from its handle, give or take 25 degrees, so that the body stands in front of it; else
    anywhere but behind it (within 110 degrees of the handle's side), as high as ``draw_camera``'s."""
    h = layout[0].T[:3, 0]  # the mug's handle sticks out along its model +x
    handle_az = np.arctan2(h[1], h[0])
    if hidden:
        azimuth = handle_az + np.pi + np.radians(rng.uniform(-1, 1) * cfg.handle_hidden_jitter)
        el = np.radians(rng.uniform(*cfg.handle_hidden_elevation))
    else:
        azimuth = handle_az + np.radians(rng.uniform(-110.0, 110.0))
        el = np.radians(rng.uniform(*cfg.cam_elevation))
    r = rng.uniform(*cfg.cam_distance)
    eye = r * np.array([np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth), np.sin(el)])
    eye[:2] += layout[0].T[:2, 3]
    return look_at(eye, np.mean([p.T[:3, 3] for p in layout], axis=0))


def handle_pixels(cfg: SynthConfig, T_cam_world: np.ndarray, mug: Placed, depth: np.ndarray,
                  shows: np.ndarray) -> int:
    """How many pixels show the mug's handle: those of ``shows`` (H, W) bool, the mug's visible pixels, whose
    surface point (from the noise-free ``depth`` (H, W), metres) lies outside the body's radius."""
    v, u = np.nonzero(shows)
    K = cfg.K()
    z = depth[v, u].astype(np.float64)
    p_cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z, np.ones_like(z)])
    p = (invert_pose(T_cam_world @ mug.T) @ p_cam)[:3]
    shape = mug.item.shape
    axis_x = item_mesh(mug.item).bounds[0, 0] + shape.radius  # the body's far side is its bounding box's -x face
    return int(np.count_nonzero(np.hypot(p[0] - axis_x, p[1]) > shape.radius + 0.0015))


def in_view(cfg: SynthConfig, T_cam_world: np.ndarray, layout: list[Placed]) -> bool:
    """Every object wholly inside the image (distractors may be cut by its border)."""
    K = cfg.K()
    for p in layout:
        v = item_mesh(p.item).apply_transform(T_cam_world @ p.T).vertices
        if np.any(v[:, 2] <= 0.05):
            return False
        uv = project(K, np.asarray(v))
        if uv.min() < 0 or np.any(uv.max(axis=0) > [cfg.width - 1, cfg.height - 1]):
            return False
    return True
