"""How the camera moved between two frames of a sequence: given by the dataset, or registered from the depth.

A sequence's frames share one table frame (``track``): frame t's ``T_cam_world`` is frame t-1's moved by the
camera's motion ``M = T_{c_t <- c_(t-1)}`` (4, 4), so that objects that do not move keep their table-frame poses.

- Given: ``scene_camera_world.json`` holds per frame the camera's pose in a fixed world frame (``R_w2c`` 9 numbers
  row-major, ``t_w2c`` mm), as a robot's kinematics would give it; that world is not the table frame, but the
  motion between two frames is the same in any fixed frame: ``M = T_c_t_w @ inv(T_c_(t-1)_w)``.
- From the depth: the new frame's points registered to the previous frame's by point-to-plane ICP (open3d),
  both seen by the same camera; the static background (table, walls) carries the registration.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.geometry import invert_pose
from workbench.io import bop
from workbench.scene import Frame

WORLD_FILE = "scene_camera_world.json"


def read_world_poses(scene_dir: Path) -> dict[int, np.ndarray] | None:
    """``scene_dir/scene_camera_world.json`` -> per image id the camera pose ``T_c_w`` (4, 4) m, world -> camera;
    None when the scene has no such file. InputError naming the file and the entry when one is malformed."""
    path = Path(scene_dir) / WORLD_FILE
    if not path.is_file():
        return None
    content = bop.expect_object(bop.read_json(path), path, "the file")
    poses = {}
    for im_id in bop.image_ids(content, path):
        entry = bop.expect_object(content[str(im_id)], path, f"image {im_id}")
        for key in ("R_w2c", "t_w2c"):
            if key not in entry:
                raise InputError(path, f"image {im_id} has no {key} (the camera's pose in the world frame: R_w2c 9 "
                                       "numbers row-major, t_w2c 3 numbers in mm)")
        poses[im_id] = bop.parse_pose(entry["R_w2c"], entry["t_w2c"], path, f"image {im_id} R_w2c/t_w2c")
    return poses


def given_motion(T_prev_c_w: np.ndarray, T_c_w: np.ndarray) -> np.ndarray:
    """The camera's motion from two world poses (4, 4) (world -> camera) -> ``M`` (4, 4): previous camera frame ->
    new camera frame. An object's pose in the new camera is ``M @ T_prev_c_obj``."""
    return T_c_w @ invert_pose(T_prev_c_w)


def depth_points(frame: Frame, stride: int = 4, max_depth: float = 3.0) -> np.ndarray:
    """The frame's depth back-projected on every ``stride``-th pixel -> (P, 3) camera frame, m (no reading and
    readings beyond ``max_depth`` m, where the sensor is noisiest, left out)."""
    K, depth = frame.camera.K, frame.depth[::stride, ::stride].astype(np.float64)
    v, u = np.nonzero((depth > 0) & (depth < max_depth))
    z = depth[v, u]
    return np.stack([(u * stride - K[0, 2]) * z / K[0, 0], (v * stride - K[1, 2]) * z / K[1, 1], z], axis=1)


def depth_motion(previous: Frame, frame: Frame, voxel: float = 0.005, max_distance: float = 0.03) -> np.ndarray:
    """The camera's motion registered from the depth -> ``M`` (4, 4), previous camera frame -> new camera frame:
    point-to-plane ICP of the new frame's points onto the previous frame's (``voxel`` m grid, correspondences up to
    ``max_distance`` m, from no motion: consecutive frames of a video are close). InputError when a frame has too
    few depth readings to register."""
    import open3d as o3d

    clouds = []
    for f in (frame, previous):
        p = depth_points(f)
        if len(p) < 100:
            raise InputError(f.source, f"too few depth readings ({len(p)}) to register the camera's motion")
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).voxel_down_sample(voxel)
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
        clouds.append(cloud)
    T = np.eye(4)
    # Coarse to fine: a wide net first, so that a few centimetres of motion are caught, then the fine fit.
    for distance in (2 * max_distance, max_distance, max_distance / 3):
        T = o3d.pipelines.registration.registration_icp(
            clouds[0], clouds[1], distance, T,
            o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=30)).transformation
    # ICP maps new camera coordinates onto the previous camera's: the motion is its inverse.
    return invert_pose(np.asarray(T))
