"""estimate_support on depth frames ray-cast in numpy: a desk against a wall, a monitor and a keyboard on it, two
boxes (the objects), the floor at the sides, Kinect-like noise and 10 % holes."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.errors import InputError
from workbench.geometry import invert_pose, make_pose, rot_z, transform_points
from workbench.problem.scene import Camera, Frame
from workbench.problem.support import depth_noise_sigma, estimate_support

W, H = 320, 240
K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])

# (centre xyz, size xyz, yaw) in the true table frame (top at z = 0).
OBJECTS = [((0.0, 0.03, 0.06), (0.08, 0.06, 0.12), 0.35), ((0.13, -0.07, 0.1), (0.15, 0.05, 0.2), -0.5)]
DESK = ((0.0, 0.0, -0.015), (0.9, 0.8, 0.03), 0.0)  # top: x in [-0.45, 0.45], y in [-0.4, 0.4]
FLOOR = ((0.0, -1.0, -0.775), (6.0, 6.0, 0.05), 0.0)  # 0.75 m below
WALL = ((0.0, 0.43, 0.3), (3.0, 0.02, 2.1), 0.0)  # 2 cm behind the desk
MONITOR = [((-0.2, 0.28, 0.3), (0.5, 0.03, 0.32), 0.0), ((-0.2, 0.3, 0.07), (0.04, 0.04, 0.14), 0.0)]  # on a stand
KEYBOARD = ((-0.15, -0.2, 0.0125), (0.44, 0.14, 0.025), 0.1)
CLUTTER = [DESK, FLOOR, WALL, *MONITOR, KEYBOARD]


def look_at(elevation: float, azimuth: float, distance: float, target=(0.03, 0.0, 0.0)) -> np.ndarray:
    """T_cam_world of an upright OpenCV camera looking at ``target`` from the -y side."""
    target = np.asarray(target)
    eye = target + distance * np.array(
        [np.cos(elevation) * np.sin(azimuth), -np.cos(elevation) * np.cos(azimuth), np.sin(elevation)]
    )
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return invert_pose(make_pose(np.stack([x, np.cross(z, x), z], axis=-1), eye))


def raycast(T_cam_world: np.ndarray, boxes) -> np.ndarray:
    """Exact z-depth (H, W) of yawed boxes (slab method in each box's frame); 0 where no box is hit."""
    v, u = np.mgrid[0:H, 0:W]
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1).reshape(-1, 3)
    T_world_cam = invert_pose(T_cam_world)
    origin, rays = T_world_cam[:3, 3], rays_cam @ T_world_cam[:3, :3].T
    best = np.full(len(rays), np.inf)
    for centre, size, yaw in boxes:
        R = rot_z(yaw)
        o = R.T @ (origin - np.asarray(centre))
        d = rays @ R
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-np.asarray(size) / 2 - o) / d
            t2 = (np.asarray(size) / 2 - o) / d
        t_near = np.nanmax(np.minimum(t1, t2), axis=1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (t_near <= t_far) & (t_near > 0)
        best = np.where(hit & (t_near < best), t_near, best)
    # Rays have unit z in the camera frame, so the ray parameter is the z-depth.
    return np.where(np.isfinite(best), best, 0.0).reshape(H, W)


def sensor(depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Axial noise growing with z^2, 10 % holes."""
    noisy = depth + rng.normal(size=depth.shape) * depth_noise_sigma(depth)
    noisy[(depth == 0) | (rng.random(depth.shape) < 0.1)] = 0.0
    return noisy.astype(np.float32)


def frame_for(T_cam_world: np.ndarray, seed: int, given: bool = False) -> Frame:
    depth = sensor(raycast(T_cam_world, OBJECTS + CLUTTER), np.random.default_rng(seed))
    return Frame(depth=depth, camera=Camera(K, W, H, T_cam_world if given else None), object_ids=[1, 2])


def box_corners(centre, size, yaw) -> np.ndarray:
    """(4, 3) footprint corners on the table."""
    sx, sy = size[0] / 2, size[1] / 2
    local = np.array([[sx, sy, 0], [-sx, sy, 0], [-sx, -sy, 0], [sx, -sy, 0]])
    return local @ rot_z(yaw).T + np.array([centre[0], centre[1], 0.0])


def assert_region_holds_objects(table, T_true_to_est: np.ndarray) -> None:
    assert_region_holds_objects_of(table, T_true_to_est, OBJECTS)


def assert_region_holds_objects_of(table, T_true_to_est: np.ndarray, objects) -> None:
    tol = 0.01
    for obj in objects:
        xy = transform_points(T_true_to_est, box_corners(*obj))[:, :2]
        assert np.all(xy >= np.array(table.region_min) - tol), (xy, table.region_min)
        assert np.all(xy <= np.array(table.region_max) + tol), (xy, table.region_max)


def assert_extent_is_desk(table, T_true_to_est: np.ndarray) -> None:
    """The extent holds the objects. Its far side (+y, away from the camera) is the desk's edge seen against the
    wall (whose foot, 2 cm behind the desk, counts). Its near side, where the desk runs out of the image's bottom,
    reaches beyond the desk: the table may go on there, and physics must not drop objects off the image border."""
    assert table.x_min < table.region_min[0] and table.region_max[0] < table.x_max
    assert table.y_min < table.region_min[1] and table.region_max[1] < table.y_max
    desk = transform_points(T_true_to_est, box_corners((0.0, 0.0, 0.0), (0.9, 0.8 + 2 * 0.02, 0.0), 0.0))
    lo, hi = desk[:, :2].min(0) - 0.01, desk[:, :2].max(0) + 0.01
    assert lo[1] < table.y_max < hi[1], (table, lo, hi)
    near_edge = transform_points(T_true_to_est, np.array([[0.0, -0.4, 0.0]]))[0]  # the desk near edge's middle
    assert table.y_min < near_edge[1] - 0.1, (table, near_edge)


@pytest.mark.parametrize(
    "elevation_deg, azimuth_deg, distance, seed", [(45, 0, 0.7, 0), (58, 15, 0.85, 1), (70, -20, 1.0, 2)]
)
def test_estimated_plane_matches_truth(elevation_deg, azimuth_deg, distance, seed):
    T_true = look_at(np.radians(elevation_deg), np.radians(azimuth_deg), distance)
    camera, table = estimate_support(frame_for(T_true, seed))

    T_est = camera.T_cam_world
    n_true, n_est = T_true[:3, 2], T_est[:3, 2]
    angle = np.degrees(np.arccos(np.clip(n_true @ n_est, -1, 1)))
    assert angle < 2.0
    # Plane offsets: distance from the camera to the table top.
    assert abs(n_true @ T_true[:3, 3] - n_est @ T_est[:3, 3]) < 0.01
    # The frame's x is the camera's x projected onto the table.
    assert T_est[0, 0] > 0.9

    T_true_to_est = invert_pose(T_est) @ T_true
    assert_region_holds_objects(table, T_true_to_est)
    assert_extent_is_desk(table, T_true_to_est)


def test_the_same_frame_gives_the_same_table_every_time():
    """Seeded runs on frames without a table pose repeat only if the support does (open3d's threaded RANSAC,
    used before, moved it by up to 0.3 mm between runs)."""
    frame = frame_for(look_at(np.radians(50), np.radians(10), 0.8), 3)
    (cam_a, table_a), (cam_b, table_b) = estimate_support(frame), estimate_support(frame)
    assert np.array_equal(cam_a.T_cam_world, cam_b.T_cam_world)
    assert table_a == table_b


def test_region_leaves_out_the_wall_behind_the_desk():
    T_true = look_at(np.radians(50), 0.0, 0.8)
    scene = OBJECTS + [DESK, FLOOR, WALL, KEYBOARD]
    depth = sensor(raycast(T_true, scene), np.random.default_rng(6))
    camera, table = estimate_support(Frame(depth=depth, camera=Camera(K, W, H), object_ids=[1, 2]))
    T_true_to_est = invert_pose(camera.T_cam_world) @ T_true
    assert_region_holds_objects(table, T_true_to_est)
    wall_foot = transform_points(T_true_to_est, np.array([0.0, 0.42, 0.0]))
    # Only the objects and the keyboard in front of them: the region ends short of the wall.
    assert table.region_max[1] < wall_foot[1] - 0.2


def test_given_extrinsics_are_kept():
    T_true = look_at(np.radians(55), np.radians(10), 0.8)
    camera, table = estimate_support(frame_for(T_true, seed=3, given=True))
    np.testing.assert_array_equal(camera.T_cam_world, T_true)
    assert_region_holds_objects(table, np.eye(4))
    assert_extent_is_desk(table, np.eye(4))


def test_wrong_extrinsics_fall_back_to_the_depth(caplog):
    T_true = look_at(np.radians(60), 0.0, 0.9)
    frame = frame_for(T_true, seed=4)
    upside_down = T_true @ make_pose(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
    frame.camera = frame.camera.with_pose(upside_down)
    camera, _ = estimate_support(frame)
    assert "does not match the depth" in caplog.text
    assert np.degrees(np.arccos(T_true[:3, 2] @ camera.T_cam_world[:3, 2])) < 2.0


def test_nothing_on_the_table_is_an_input_error():
    T_true = look_at(np.radians(60), 0.0, 0.9)
    depth = sensor(raycast(T_true, [DESK, FLOOR]), np.random.default_rng(5))
    with pytest.raises(InputError, match="nothing stands on the table"):
        estimate_support(Frame(depth=depth, camera=Camera(K, W, H), object_ids=[1]))


def test_a_stack_taller_than_the_height_limit_is_still_the_object_region(caplog):
    """Clusters over max_height (40 cm) are dropped as walls and monitors; when nothing else stands on the table (a
    cracker box with a wood block stood on it, 41 cm), they are the region, with a warning."""
    T_true = look_at(np.radians(50), 0.0, 1.0)
    stack = [((0.0, 0.0, 0.105), (0.16, 0.06, 0.21), 0.3), ((0.0, 0.0, 0.31), (0.085, 0.085, 0.2), 0.3)]
    depth = sensor(raycast(T_true, [DESK, FLOOR, *stack]), np.random.default_rng(7))
    camera, table = estimate_support(Frame(depth=depth, camera=Camera(K, W, H), object_ids=[1, 5]))
    assert "nothing stands on the table up to 40 cm" in caplog.text
    assert_region_holds_objects_of(table, invert_pose(camera.T_cam_world) @ T_true, stack)


def test_a_stack_taller_than_the_height_limit_beside_another_object_stays_in_when_the_objects_can_be_it():
    """A cracker box with a wood block stood on it (41 cm) beside a small box: the stack is the listed objects'
    when they reach that high stacked and the volume seen in it is theirs; objects that could not be it (too small,
    or too short to reach 41 cm) leave it out as a wall or a monitor."""
    T_true = look_at(np.radians(50), 0.0, 1.0)
    stack = [((0.15, -0.1, 0.105), (0.16, 0.06, 0.21), 0.3), ((0.15, -0.1, 0.31), (0.085, 0.085, 0.2), 0.3)]
    small = [((-0.1, 0.0, 0.06), (0.08, 0.06, 0.12), 0.35)]
    depth = sensor(raycast(T_true, [DESK, FLOOR, *stack, *small]), np.random.default_rng(8))
    frame = Frame(depth=depth, camera=Camera(K, W, H), object_ids=[1, 5, 2])
    volume = sum(np.prod(size) for _, size, _ in stack + small)

    camera, table = estimate_support(frame, objects_volume=volume, objects_reach=0.21 + 0.2 + 0.12)
    assert_region_holds_objects_of(table, invert_pose(camera.T_cam_world) @ T_true, stack + small)

    for objects_volume, objects_reach in [(volume / 3, 0.53), (volume, 0.35), (None, None)]:
        camera, table = estimate_support(frame, objects_volume=objects_volume, objects_reach=objects_reach)
        T_true_to_est = invert_pose(camera.T_cam_world) @ T_true
        assert_region_holds_objects_of(table, T_true_to_est, small)
        stack_far_corner = transform_points(T_true_to_est, box_corners(*stack[0]))[:, 0].max()
        assert table.region_max[0] < stack_far_corner - 0.05
