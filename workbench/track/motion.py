"""How the camera moved between two frames of a sequence: given by the dataset, or registered from the depth.

A sequence's frames share one table frame (``track``): frame t's ``T_cam_world`` is frame t-1's moved by the
camera's motion ``M = T_{c_t <- c_(t-1)}`` (4, 4), so that objects that do not move keep their table-frame poses.

- Given: ``scene_camera_world.json`` holds per frame the camera's pose in a fixed world frame (``R_w2c`` 9 numbers
  row-major, ``t_w2c`` mm), as a robot's kinematics would give it; that world is not the table frame, but the
  motion between two frames is the same in any fixed frame: ``M = T_c_t_w @ inv(T_c_(t-1)_w)``.
- From the depth: the new frame's points registered to the previous frame's by point-to-plane ICP (open3d),
  both seen by the same camera, kept to what stands on the table (``near_objects``): the objects' faces fix what
  the table's plane would leave free.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.geometry import invert_pose, transform_points
from workbench.io import bop, readers
from workbench.problem.scene import Frame

WORLD_FILE = "scene_camera_world.json"


def read_world_poses(scene_dir: Path) -> dict[int, np.ndarray] | None:
    """``scene_dir/scene_camera_world.json`` -> per image id the camera pose ``T_c_w`` (4, 4) m, world -> camera;
    None when the scene has no such file. InputError naming the file and the entry when one is malformed."""
    path = Path(scene_dir) / WORLD_FILE
    if not path.is_file():
        return None
    content = readers.expect_object(readers.read_json(path), path, "the file")
    poses = {}
    for im_id in bop.image_ids(content, path):
        entry = readers.expect_object(content[str(im_id)], path, f"image {im_id}")
        for key in ("R_w2c", "t_w2c"):
            if key not in entry:
                raise InputError(path, f"image {im_id} has no {key} (the camera's pose in the world frame: R_w2c 9 "
                                       "numbers row-major, t_w2c 3 numbers in mm)")
        poses[im_id] = readers.parse_pose(entry["R_w2c"], entry["t_w2c"], path, f"image {im_id} R_w2c/t_w2c")
    return poses


def given_motion(T_prev_c_w: np.ndarray, T_c_w: np.ndarray) -> np.ndarray:
    """The camera's motion from two world poses (4, 4) (world -> camera) -> ``M`` (4, 4): previous camera frame ->
    new camera frame. An object's pose in the new camera is ``M @ T_prev_c_obj``."""
    return T_c_w @ invert_pose(T_prev_c_w)


def depth_points(frame: Frame, stride: int = 2, max_depth: float = 3.0) -> np.ndarray:
    """The frame's depth back-projected on every ``stride``-th pixel -> (P, 3) camera frame, m (no reading and
    readings beyond ``max_depth`` m, where the sensor is noisiest, left out)."""
    K, depth = frame.camera.K, frame.depth[::stride, ::stride].astype(np.float64)
    v, u = np.nonzero((depth > 0) & (depth < max_depth))
    z = depth[v, u]
    return np.stack([(u * stride - K[0, 2]) * z / K[0, 0], (v * stride - K[1, 2]) * z / K[1, 1], z], axis=1)


def near_objects(points: np.ndarray, T_cam_world: np.ndarray, region: tuple[np.ndarray, np.ndarray],
                 margin: float = 0.1, min_height: float = 0.01, max_height: float = 0.4) -> np.ndarray:
    """(P,) bool: the camera-frame ``points`` (P, 3) over the table's object ``region`` ((lo, hi) (2,) table-frame x,
    y, m) widened by ``margin`` m, from ``min_height`` to ``max_height`` m above the table: what stands on it, as
    the table frame ``T_cam_world`` (4, 4) places it."""
    p = transform_points(invert_pose(T_cam_world), points)
    lo, hi = np.asarray(region[0]) - margin, np.asarray(region[1]) + margin
    return np.all((p[:, :2] >= lo) & (p[:, :2] <= hi), axis=1) & (p[:, 2] > min_height) & (p[:, 2] < max_height)


def depth_motion(previous: Frame, frame: Frame, T_cam_world: np.ndarray, region: tuple[np.ndarray, np.ndarray],
                 voxel: float = 0.003, max_distance: float = 0.03) -> np.ndarray:
    """The camera's motion registered from the depth -> ``M`` (4, 4), previous camera frame -> new camera frame:
    point-to-plane ICP of the new frame's points onto the previous frame's, both kept to what stands on the table
    (``near_objects``, ``T_cam_world`` the previous frame's table frame, ``region`` its object region): the table is
    a plane that ICP slides along, which held the fit at no motion on generated frames, and far walls are the
    noisiest readings; the objects' faces fix every direction. On a ``voxel`` m grid,
    correspondences from ``2 * max_distance`` down to ``max_distance / 3`` m, starting from no motion (consecutive
    frames of a video are close). InputError when a frame has too few readings there to register."""
    import open3d as o3d

    clouds = []
    for f in (frame, previous):
        p = depth_points(f)
        p = p[near_objects(p, T_cam_world, region)]
        if len(p) < 100:
            raise InputError(f.source, f"too few depth readings ({len(p)}) near the objects to register the camera's "
                                       "motion")
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).voxel_down_sample(voxel)
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
        clouds.append(cloud)
    T = np.eye(4)
    for distance in (2 * max_distance, max_distance, max_distance / 3):  # a wide net first, then the fine fit
        T = o3d.pipelines.registration.registration_icp(
            clouds[0], clouds[1], distance, T,
            o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50)).transformation
    # ICP maps new camera coordinates onto the previous camera's: the motion is its inverse.
    return invert_pose(np.asarray(T))
