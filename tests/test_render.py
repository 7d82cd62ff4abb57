"""Batched depth renderer against analytic depth and against itself (batch vs single, passes, backends)."""

from __future__ import annotations

import multiprocessing

import numpy as np
import pytest
import trimesh

from workbench.errors import InputError
from workbench.geometry import invert_pose, make_pose, pose_from_xyz_rpy
from workbench.problem.scene import Camera
from workbench.render.depth import BACKENDS, DepthRenderer, RenderConfig, render_depth, render_mesh
from workbench.render.likelihood import ImageTerms, LikelihoodConfig, scene_loglik
from workbench.render.shared import common_poses, draw_shared, drawn_loglik, render_shared

pytestmark = pytest.mark.slow  # needs OpenGL

BOX = np.array([0.10, 0.06, 0.04])
W, H = 160, 120


def look_at(eye, target) -> np.ndarray:
    """T_cam_world of an OpenCV camera at ``eye`` looking at ``target``, table z up. -> (4, 4)."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return invert_pose(make_pose(np.stack([x, np.cross(z, x), z], axis=1), np.asarray(eye, float)))


# Principal point off the half-pixel grid so that a half-pixel convention error moves silhouettes.
CAMERA = Camera(
    K=np.array([[300.0, 0.0, 80.3], [0.0, 310.0, 58.7], [0.0, 0.0, 1.0]]),
    width=W,
    height=H,
    T_cam_world=look_at([0.05, -0.55, 0.45], [0.0, 0.0, 0.03]),
)


def analytic_box_depth(camera: Camera, extents: np.ndarray, T_world_box: np.ndarray) -> np.ndarray:
    """Camera-z depth of a box centred in its frame, ray through each pixel centre per K. -> (H, W), 0 = miss."""
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(camera.K).T  # (H, W, 3), z = 1
    T_box_cam = invert_pose(camera.T_cam_world @ T_world_box)
    origin, direction = T_box_cam[:3, 3], rays @ T_box_cam[:3, :3].T
    with np.errstate(divide="ignore"):
        t1, t2 = (-extents / 2 - origin) / direction, (extents / 2 - origin) / direction
    t_near, t_far = np.minimum(t1, t2).max(axis=-1), np.maximum(t1, t2).min(axis=-1)
    hit = (t_near <= t_far) & (t_near > 0)
    return np.where(hit, t_near, 0.0)  # ray z is 1, so the ray parameter is camera z


def eroded(mask: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood lies entirely in ``mask``. (H, W) -> (H, W)."""
    padded = np.pad(mask, 1)
    out = np.ones_like(mask)
    for dy in range(3):
        for dx in range(3):
            out &= padded[dy : dy + mask.shape[0], dx : dx + mask.shape[1]]
    return out


def assert_same_depth(actual: np.ndarray, desired: np.ndarray) -> None:
    """Equal to 1e-5 m except at a few pixels per image. A tile's window position changes float rounding before
    the rasteriser snaps vertices to 1/256 px, which moves depth by that much along grazing surfaces and can flip a
    pixel whose centre lies on an edge; a bleed or a mixed-up tile changes hundreds of pixels. (..., H, W)."""
    differs = np.abs(actual - desired) > 1e-5
    assert actual.shape == desired.shape
    assert differs.reshape(-1, H * W).sum(axis=1).max() <= 10, f"{differs.sum()} pixels differ"


def random_particles(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """Objects scattered over and around the view, some crossing the image border. -> (n, k, 4, 4)."""
    xyz = rng.uniform([-0.25, -0.15, 0.0], [0.25, 0.2, 0.1], size=(n, k, 3))
    rpy = rng.uniform(-np.pi, np.pi, size=(n, k, 3))
    return pose_from_xyz_rpy(np.concatenate([xyz, rpy], axis=-1))


@pytest.fixture(scope="module")
def meshes() -> list[trimesh.Trimesh]:
    return [trimesh.creation.box(BOX), trimesh.creation.icosphere(subdivisions=2, radius=0.035)]


@pytest.fixture(scope="module")
def renderer(meshes):
    with DepthRenderer(CAMERA, meshes) as r:
        yield r


def test_rotated_box_matches_analytic_depth():
    T_world_box = pose_from_xyz_rpy([0.02, 0.01, 0.05, 0.4, -0.3, 0.7])
    expected = analytic_box_depth(CAMERA, BOX, T_world_box)
    depth = render_depth(CAMERA, [trimesh.creation.box(BOX)], T_world_box[None])

    assert depth.dtype == np.float32 and depth.shape == (H, W)
    inside = eroded(expected > 0)
    assert inside.sum() > 500
    assert np.abs(depth[inside] - expected[inside]).max() < 1e-3
    # Silhouettes agree up to pixels whose centre grazes an edge; a half-pixel offset would flip whole rows.
    assert np.count_nonzero((depth > 0) != (expected > 0)) <= 3
    assert np.all(depth[eroded(expected == 0)] == 0.0)


def test_batch_tiles_equal_single_renders(renderer):
    particles = random_particles(np.random.default_rng(0), 9, 2)
    batch = renderer.render(particles)

    assert batch.shape == (9, H, W)
    borders = [np.concatenate([d[0], d[-1], d[:, 0], d[:, -1]]) for d in batch]
    assert sum(np.any(b > 0) for b in borders) >= 2, "some particle should reach past its tile"
    for i, particle in enumerate(particles):
        alone = renderer.render(particle[None])[0]
        assert np.count_nonzero(alone) > 0
        assert_same_depth(batch[i], alone)


def test_batch_larger_than_one_pass(renderer, meshes):
    particles = random_particles(np.random.default_rng(1), 13, 2)
    with DepthRenderer(CAMERA, meshes, RenderConfig(max_framebuffer=400)) as small:
        assert small.particles_per_pass == 6  # 2 columns x 3 rows of 160x120
        split = small.render(particles)
    assert_same_depth(split, renderer.render(particles))


def test_no_bleed_into_neighbour_tiles(meshes):
    nothing = invert_pose(CAMERA.T_cam_world) @ make_pose(np.eye(3), [0.0, 0.0, -1.0])  # behind the camera
    filling = invert_pose(CAMERA.T_cam_world) @ make_pose(np.eye(3), [0.0, 0.0, 0.1])  # box overfills the view
    particles = np.stack([[nothing, nothing]] * 12)
    particles[5, 0] = filling  # column-major 3x4 tiles: tile 5 is surrounded by tiles 0-2, 4, 6, 8-10
    with DepthRenderer(CAMERA, meshes, RenderConfig(max_framebuffer=480)) as small:
        assert small.particles_per_pass == 12
        depth = small.render(particles)
    assert np.all(depth[5] > 0)
    assert np.all(np.delete(depth, 5, axis=0) == 0.0)


def test_two_objects_occlude(meshes):
    front = pose_from_xyz_rpy([0.0, -0.05, 0.1, 0.0, 0.0, 0.3])  # floating: rendering ignores physics
    back = pose_from_xyz_rpy([0.01, 0.12, 0.0, 0.0, 0.0, -0.2])
    with DepthRenderer(CAMERA, [meshes[0], meshes[0]]) as both, DepthRenderer(CAMERA, meshes[:1]) as one:
        together = both.render(np.stack([front, back])[None])[0]
        d_front, d_back = one.render(np.stack([front[None], back[None]]))

    overlap = (d_front > 0) & (d_back > 0)
    assert overlap.sum() > 50
    assert np.all(d_front[overlap] < d_back[overlap])
    expected = np.where(overlap, np.minimum(d_front, d_back), d_front + d_back)
    np.testing.assert_allclose(together, expected, atol=1e-5, rtol=0)


def test_objects_left_out_are_not_drawn(renderer, meshes):
    particles = random_particles(np.random.default_rng(2), 7, 2)
    drawn = np.array([[True, True], [True, False], [False, True], [False, False], [True, False], [True, False],
                      [False, True]])
    depth = renderer.render(particles, drawn)
    with DepthRenderer(CAMERA, meshes[:1]) as box, DepthRenderer(CAMERA, meshes[1:]) as ball:
        boxes, balls = box.render(particles[:, :1]), ball.render(particles[:, 1:])
    expected = [boxes[i] if d[0] and not d[1] else balls[i] if d[1] and not d[0] else None for i, d in enumerate(drawn)]
    for i, e in enumerate(expected):
        if e is not None:
            assert_same_depth(depth[i], e)
    assert np.all(depth[3] == 0.0)
    assert_same_depth(depth[0], renderer.render(particles[:1])[0])
    with pytest.raises(ValueError, match="drawn"):
        renderer.render(particles, drawn[:, :1])


def test_common_poses_find_what_scenes_share():
    scenes = random_particles(np.random.default_rng(3), 5, 3)
    scenes[:, 1] = scenes[0, 1]  # every scene has object 1 in one pose
    scenes[2:4, 0] = scenes[4, 0]  # three of five have object 0 in one pose
    common, shared = common_poses(scenes)
    np.testing.assert_array_equal(shared, [[False, True, False], [False, True, False], [True, True, False],
                                           [True, True, False], [True, True, False]])
    np.testing.assert_array_equal(common[:2], [scenes[4, 0], scenes[0, 1]])


def test_shared_poses_drawn_once_give_the_same_depth(meshes):
    """Settling's batches: each scene moves one object of a common scene. Drawing the unmoved ones once per batch
    gives each scene's depth, occlusions between moved and unmoved objects included."""
    rng = np.random.default_rng(4)
    base = np.stack([pose_from_xyz_rpy([0.0, -0.05, 0.06, 0.0, 0.0, 0.3]),  # the box in front of the ball
                     pose_from_xyz_rpy([0.01, 0.05, 0.03, 0.0, 0.0, 0.0]),
                     pose_from_xyz_rpy([-0.12, 0.02, 0.05, 0.2, 0.1, 0.0])])
    scenes = np.repeat(base[None], 16, axis=0)
    for i in range(15):  # the last scene is the common one itself
        k = i % 3
        scenes[i, k, :3, 3] += rng.normal(0.0, 0.03, 3)
    scenes[3, 0, :3, 3] = [0.018, -0.075, 0.12]  # the box lifted between the camera and the ball
    with DepthRenderer(CAMERA, [meshes[0], meshes[1], meshes[0]]) as r:
        plain, shared = r.render(scenes), render_shared(r, scenes)
        all_moved = random_particles(rng, 4, 3)  # nothing shared: drawn as they are
        np.testing.assert_array_equal(render_shared(r, all_moved), r.render(all_moved))
        box = r.render(scenes[3:4], np.array([[True, False, False]]))[0]
        ball = r.render(scenes[3:4], np.array([[False, True, False]]))[0]
    assert_same_depth(shared, plain)
    hidden = (box > 0) & (ball > 0)  # the lifted box (moved) in front of the ball (shared)
    assert hidden.sum() > 50 and np.all(box[hidden] < ball[hidden])
    assert np.abs(shared[3][hidden] - box[hidden]).max() < 1e-5


@pytest.mark.parametrize("floor", [None, 2.0])
def test_shared_scenes_scored_by_their_own_pixels(meshes, floor):
    """Each scene's log-likelihood from its shared tile's and its own objects' pixels is the composite's, with and
    without the clutter floor (which the pixels an object uncovers score)."""
    rng = np.random.default_rng(5)
    base = np.stack([pose_from_xyz_rpy([0.0, -0.05, 0.02, 0.0, 0.0, 0.3]),
                     pose_from_xyz_rpy([0.06, 0.05, 0.035, 0.0, 0.0, 0.0])])
    scenes = np.repeat(base[None], 9, axis=0)
    for i in range(8):
        scenes[i, i % 2, :3, 3] += rng.normal(0.0, 0.01, 3)
    config = LikelihoodConfig(clutter_floor=floor)
    with DepthRenderer(CAMERA, meshes) as r:
        truth = r.render(base[None])[0]
        background = np.full((H, W), 0.75, dtype=np.float32)
        observed = np.where(truth > 0, truth + rng.normal(0.0, 0.003, truth.shape), background).astype(np.float32)
        observed[::7, ::5] = 0.0  # holes: no reading
        drawn = draw_shared(r, scenes)
        assert len(drawn.groups) == 3  # sharing the box, the ball, both (the common scene itself)
        incremental, gain = drawn_loglik(drawn, observed, background, config)
        composite = scene_loglik(observed, background, render_shared(r, scenes), config)
        _, composite_gain = ImageTerms.of(observed, background, config).scene(render_shared(r, scenes))
        plain = scene_loglik(observed, background, r.render(scenes), config)
    np.testing.assert_allclose(incremental, composite, rtol=0, atol=1e-6 * np.abs(composite).max())
    np.testing.assert_allclose(gain, composite_gain, rtol=0, atol=1e-6 * np.abs(composite).max())
    assert floor is not None or not gain.any()  # the floor's part is nothing when it is off
    assert np.abs(incremental - plain).max() < 25.0  # a few edge pixels rasterised in another tile
    assert np.argmax(incremental) == 8 and np.ptp(incremental) > 1000.0  # the truth wins, by far


def test_empty_pixels_are_exactly_zero(renderer):
    behind_camera = invert_pose(CAMERA.T_cam_world) @ make_pose(np.eye(3), [0.0, 0.0, -1.0])
    nothing = renderer.render(np.stack([behind_camera, behind_camera])[None])
    assert np.all(nothing == 0.0)
    assert renderer.render(np.zeros((0, 2, 4, 4))).shape == (0, H, W)


def test_other_backend_in_same_process_is_refused(renderer, meshes):
    other = next(b for b in BACKENDS if b != renderer.backend)
    with pytest.raises(InputError, match="once per process"):
        DepthRenderer(CAMERA, meshes, RenderConfig(backend=other))


def _render_in_spawned_worker(meshes, particle, backend: str) -> np.ndarray:
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        return pool.apply_async(render_depth, (CAMERA, meshes, particle, RenderConfig(backend=backend))).get(120)


def test_spawned_worker_renders_the_same(renderer, meshes):
    particle = random_particles(np.random.default_rng(2), 1, 2)[0]
    depth = _render_in_spawned_worker(meshes, particle, renderer.backend)
    assert np.count_nonzero(depth) > 0
    np.testing.assert_allclose(depth, renderer.render(particle[None])[0], atol=1e-5, rtol=0)


def test_egl_matches_osmesa(renderer, meshes):
    other = next(b for b in BACKENDS if b != renderer.backend)
    particle = random_particles(np.random.default_rng(3), 1, 2)[0]
    try:
        depth = _render_in_spawned_worker(meshes, particle, other)
    except RuntimeError as e:
        if "could not create" in str(e):
            pytest.skip(f"{other} unavailable: {e}")
        raise
    assert np.count_nonzero(depth) > 0
    np.testing.assert_allclose(depth, renderer.render(particle[None])[0], atol=1e-5, rtol=0)


def test_decimated_render_stays_within_the_depth_bound():
    # A finely tessellated bottle-like solid of revolution (~16k faces), turned and seen from the test camera.
    z = np.linspace(0.0, 0.12, 64)
    r = 0.03 + 0.008 * np.sin(z / 0.12 * 2 * np.pi)
    profile = np.concatenate([[[0.0, 0.0]], np.stack([r, z], axis=1), [[0.0, 0.12]]])
    full = trimesh.creation.revolve(profile, sections=128)
    bound = 1e-3
    simple = render_mesh(full, bound)
    assert len(simple.faces) <= len(full.faces) / 4  # it did simplify
    poses = pose_from_xyz_rpy(np.array([[[0.0, 0.0, 0.0, 0.0, 0.0, 0.0]], [[0.02, 0.03, 0.035, 1.2, 0.3, 0.5]]]))
    with DepthRenderer(CAMERA, [full], RenderConfig(max_depth_error=0.0)) as exact, \
            DepthRenderer(CAMERA, [full], RenderConfig(max_depth_error=bound)) as decimated:
        assert len(decimated.meshes[0].faces) == len(simple.faces)
        a, b = exact.render(poses), decimated.render(poses)
    inside = np.stack([eroded(x > 0) for x in a]) & (b > 0)  # silhouette pixels straddle an edge
    assert inside.sum() > 1000
    error = np.abs(a - b)[inside]
    assert np.percentile(error, 99) <= bound and np.max(error) < 3 * bound


def test_back_face_culling_leaves_closed_meshes_unchanged(renderer, meshes):
    particles = random_particles(np.random.default_rng(3), 12, 2)
    with DepthRenderer(CAMERA, meshes, RenderConfig(cull_back_faces=False)) as whole:
        assert_same_depth(renderer.render(particles), whole.render(particles))


def test_open_mesh_is_drawn_with_its_back_faces():
    # A box without its top, seen from above: the floor and the far walls are seen from inside, as back faces.
    box = trimesh.creation.box(BOX)
    tray = trimesh.Trimesh(box.vertices, box.faces[box.face_normals[:, 2] < 0.5])
    assert not tray.is_watertight
    pose = pose_from_xyz_rpy(np.array([[[0.0, 0.0, 0.02, 0.0, 0.0, 0.0]]]))
    with DepthRenderer(CAMERA, [tray]) as culled, \
            DepthRenderer(CAMERA, [tray], RenderConfig(cull_back_faces=False)) as whole:
        depth = culled.render(pose)[0]
        assert_same_depth(depth, whole.render(pose)[0])
    closed = render_depth(CAMERA, [box], pose[0])
    inside = eroded(closed > 0)
    assert np.mean(depth[inside] > closed[inside] + 0.01) > 0.3  # the floor, deeper than the missing lid


def test_a_thin_object_scores_at_its_place_above_laid_on_a_distractor_beside_it():
    """A 1.6 cm thin slab (scissors) on the table and, beside it, a 5 cm block nobody modelled: rendered here, the
    observed depth holds both. Laid on the block, the slab covers part of the block's top (its own top 1.6 cm above
    the block's) and leaves its own pixels to the table; at its true place it explains them. The plain outlier
    mixture prefers the block (an unexplained reading is an outlier, covering it gains about 7 per pixel, and a
    thin object's own pixels gain about 1.3); with the clutter floor the truth wins."""
    from workbench.problem.problem import table_depth
    from workbench.problem.scene import Table

    slab, block = trimesh.creation.box((0.18, 0.05, 0.016)), trimesh.creation.box((0.22, 0.12, 0.05))
    truth = make_pose(np.eye(3), np.array([-0.06, -0.06, 0.008]))
    T_block = make_pose(np.eye(3), np.array([0.04, 0.06, 0.025]))
    laid = make_pose(np.eye(3), np.array([0.04, 0.06, 0.05 + 0.008]))
    with DepthRenderer(CAMERA, [slab, block]) as both, DepthRenderer(CAMERA, [slab]) as alone:
        observed = both.render(np.stack([truth, T_block])[None])[0]
        rendered = alone.render(np.stack([truth, laid])[:, None])
    background = table_depth(CAMERA, Table(-0.4, 0.4, -0.4, 0.4))
    observed = np.where(observed > 0, observed, background)
    assert (rendered[0] > 0).sum() > 50 and (rendered[1] > 0).sum() > 50
    plain = scene_loglik(observed, background, rendered, LikelihoodConfig(clutter_floor=None))
    floor = scene_loglik(observed, background, rendered, LikelihoodConfig(clutter_floor=2.0))
    assert plain[1] > plain[0]
    assert floor[0] > floor[1]
