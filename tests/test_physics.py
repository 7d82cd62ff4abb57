"""Physics projection with real pybullet: settling, separation, failure statuses, determinism, collision shapes."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import trimesh

from workbench.errors import InputError
from workbench.geometry import pose_from_xyz_rpy
from workbench.physics import (
    STATUS_OFF_TABLE,
    STATUS_REST,
    STATUS_STEP_CAP,
    STATUS_UNSTABLE,
    PhysicsConfig,
    PhysicsProjector,
)
from workbench.physics.collision import collision_shape_for
from workbench.problem.scene import ObjectModel, Table

pytestmark = pytest.mark.slow  # needs pybullet

TABLE = Table(-0.3, 0.3, -0.3, 0.3)
MM = 1e-3


def box(extents, obj_id=1) -> ObjectModel:
    return ObjectModel(obj_id, trimesh.creation.box(extents=extents))


def cylinder(radius=0.03, height=0.1, obj_id=2) -> ObjectModel:
    return ObjectModel(obj_id, trimesh.creation.cylinder(radius=radius, height=height, sections=32))


def cup_mesh() -> trimesh.Trimesh:
    """A watertight cup 8 cm wide, 9 cm tall, 5 mm walls, standing on z = 0 in its own frame."""
    r, h, t = 0.04, 0.09, 0.005
    profile = np.array([[0, 0], [r, 0], [r, h], [r - t, h], [r - t, t], [0, t], [0, 0]])
    return trimesh.creation.revolve(profile, sections=32)


def poses(*xyz_rpy) -> np.ndarray:
    return pose_from_xyz_rpy(np.array(xyz_rpy, dtype=np.float64))


def tilt(T: np.ndarray) -> np.ndarray:
    """Angle between an object's z axis and the table's (radians). (..., 4, 4) -> (...)."""
    return np.arccos(np.clip(T[..., 2, 2], -1.0, 1.0))


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("vhacd")


def test_box_dropped_from_5cm_rests_upright():
    with PhysicsProjector([box([0.1, 0.06, 0.04])], TABLE) as projector:
        out, status, steps = projector.project(poses([0.02, -0.01, 0.02 + 0.05, 0, 0, 0.3]))
    assert status == STATUS_REST
    assert 0 < steps < projector.config.max_steps
    assert abs(out[0, 2, 3] - 0.02) < 2 * MM
    assert tilt(out[0]) < np.radians(1)
    assert np.linalg.norm(out[0, :2, 3] - [0.02, -0.01]) < 2 * MM


def test_interpenetrating_boxes_are_pushed_apart_not_launched():
    # Two 6 cm cubes overlapping by 2 cm sideways, the second also sunk 1.5 cm into the table.
    models = [box([0.06, 0.06, 0.06], 1), box([0.06, 0.06, 0.06], 2)]
    start = poses([0.0, 0, 0.03, 0, 0, 0], [0.04, 0, 0.015, 0, 0, 0])
    with PhysicsProjector(models, TABLE) as projector:
        out, status, _ = projector.project(start)
    assert status == STATUS_REST
    np.testing.assert_allclose(out[:, 2, 3], 0.03, atol=2 * MM)  # both on the table
    assert np.all(tilt(out) < np.radians(2))
    assert out[1, 0, 3] - out[0, 0, 3] > 0.06 - 2 * MM  # upright, aligned cubes: no penetration deeper than 2 mm
    # Pushed apart by the overlap, half each (left to Bullet, one moves ~2 cm and the other stays).
    moved = np.linalg.norm(out[:, :2, 3] - start[:, :2, 3], axis=1)
    np.testing.assert_allclose(moved, 0.01, atol=3 * MM)


def test_box_overhanging_the_edge_falls_off():
    # Centre of mass 3 cm beyond the table's edge at x = 0.3.
    with PhysicsProjector([box([0.1, 0.06, 0.04])], TABLE) as projector:
        out, status, _ = projector.project(poses([0.33, 0, 0.02, 0, 0, 0]))
    assert status == STATUS_OFF_TABLE
    assert out[0, 2, 3] < projector.config.off_table_z


def test_small_box_stays_stacked_on_large_one():
    models = [box([0.2, 0.15, 0.05], 1), box([0.05, 0.05, 0.05], 2)]
    start = poses([0, 0, 0.025, 0, 0, 0], [0.01, 0.01, 0.05 + 0.025 + 0.003, 0, 0, 0.4])  # 3 mm above
    with PhysicsProjector(models, TABLE) as projector:
        out, status, _ = projector.project(start)
    assert status == STATUS_REST
    assert abs(out[1, 2, 3] - 0.075) < 2 * MM
    assert np.linalg.norm(out[1, :2, 3] - [0.01, 0.01]) < 5 * MM
    assert tilt(out[1]) < np.radians(1)


def test_box_leaning_on_another_ends_at_rest():
    # A 2 x 6 x 12 cm board tilted 20 degrees about y, its top against the side of a 10 cm cube.
    models = [box([0.1, 0.1, 0.1], 1), box([0.02, 0.06, 0.12], 2)]
    lean = np.radians(20)
    x = -0.05 - 0.06 * np.sin(lean) - 0.01 * np.cos(lean) - 0.002
    start = poses([0, 0, 0.05, 0, 0, 0], [x, 0, 0.06 * np.cos(lean) + 0.01 * np.sin(lean) + 0.002, 0, lean, 0])
    with PhysicsProjector(models, TABLE) as projector:
        out, status, steps = projector.project(start)
    assert status == STATUS_REST and steps < projector.config.max_steps
    assert abs(out[0, 2, 3] - 0.05) < 2 * MM and tilt(out[0]) < np.radians(1)  # the support did not move
    # Still leaning against the cube, or lying flat on its broad face.
    leaning = np.radians(5) < tilt(out[1]) < np.radians(60) and out[1, 0, 3] < -0.05
    flat = abs(abs(out[1, 0, 2]) - 1) < 0.02 and abs(out[1, 2, 3] - 0.01) < 2 * MM
    assert leaning or flat
    # Its lowest corner is on the table, not in it.
    corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T * [0.01, 0.03, 0.06]
    lowest = np.min(corners @ out[1, :3, :3].T[:, 2] + out[1, 2, 3])
    assert abs(lowest) < 2 * MM


def test_cylinder_settles_upright_on_its_flat_face():
    with PhysicsProjector([cylinder()], TABLE) as projector:
        out, status, _ = projector.project(poses([0, 0, 0.05 + 0.02, np.radians(5), 0, 0]))
    assert status == STATUS_REST
    assert tilt(out[0]) < np.radians(1)
    assert abs(out[0, 2, 3] - 0.05) < 2 * MM


def test_cup_stands_on_its_base(cache_dir):
    with PhysicsProjector([ObjectModel(3, cup_mesh())], TABLE, cache_dir=cache_dir) as projector:
        out, status, _ = projector.project(poses([0, 0, 0.01, 0, 0, 0]))
    assert status == STATUS_REST
    assert tilt(out[0]) < np.radians(1)
    # V-HACD's pieces are about a voxel larger than the mesh, and Bullet pads each by 1 mm.
    assert abs(out[0, 2, 3]) < 3 * MM


def test_result_depends_only_on_the_particle_itself(cache_dir):
    models = [box([0.08, 0.05, 0.04], 1), cylinder(obj_id=2), ObjectModel(3, cup_mesh())]
    shapes = [collision_shape_for(m.mesh, cache_dir=cache_dir) for m in models]
    a = poses([0, 0, 0.01, 0.3, 0.2, 0], [0.05, 0.02, 0.04, 1.2, 0, 0.5], [-0.05, 0.03, 0.0, 0, 0.1, 0])
    b = poses([0.1, 0, 0.1, 0, 0, 0], [0.1, 0.01, 0.2, 0, 0, 0], [-0.1, -0.1, 0.05, 2.0, 0, 0])
    with PhysicsProjector(models, TABLE, shapes=shapes) as projector:
        first = projector.project(a)
        projector.project(b)
        again = projector.project(a)
        # The rest pose of a, restarted: the sharpest test of contact state left over from the previous particle.
        rest = projector.project(first[0])
    with PhysicsProjector(models, TABLE, shapes=shapes) as fresh:
        alone = fresh.project(a)
        rest_alone = fresh.project(first[0])
    assert first[1] == STATUS_REST
    for other in (again, alone):
        assert np.array_equal(first[0], other[0]) and first[1:] == other[1:]
    assert np.array_equal(rest[0], rest_alone[0]) and rest[1:] == rest_alone[1:]


def test_a_sleeping_body_is_woken_when_something_falls_on_it():
    # A 3 cm cube rests from the start, so it is asleep after the first two checks; a 20 cm board standing on its
    # edge, tilted 23 degrees towards it, topples onto it a few tenths of a second later and shoves it.
    models = [box([0.03, 0.03, 0.03], 1), box([0.06, 0.06, 0.2], 2)]
    lean = 0.4
    start = poses([0, 0, 0.015, 0, 0, 0], [-0.12, 0, 0.1 * np.cos(lean) + 0.03 * np.sin(lean) + 0.002, 0, lean, 0])
    results = {}
    for sleep in (True, False):
        with PhysicsProjector(models, TABLE, PhysicsConfig(sleep_calm=sleep)) as projector:
            results[sleep] = projector.project(start)
    (out, status, _), (awake, _, _) = results[True], results[False]
    assert status == STATUS_REST
    assert np.linalg.norm(out[0, :3, 3] - start[0, :3, 3]) > 3 * MM  # a cube left asleep would not move at all
    assert tilt(out[0]) > np.radians(2)  # the board rests propped on it
    assert np.max(np.linalg.norm(out[:, :3, 3] - awake[:, :3, 3], axis=1)) < 1 * MM


def test_sleeping_calm_bodies_hardly_moves_resting_poses():
    rng = np.random.default_rng(4)
    models = [box(rng.uniform(0.03, 0.1, 3), k) for k in range(4)]
    xyz = np.concatenate([rng.uniform(-0.12, 0.12, (30, 4, 2)), rng.uniform(0.03, 0.12, (30, 4, 1))], axis=2)
    rpy = rng.uniform(-np.pi, np.pi, (30, 4, 3))
    starts = pose_from_xyz_rpy(np.concatenate([xyz, rpy], axis=2))
    out = {}
    for sleep in (True, False):
        with PhysicsProjector(models, TABLE, PhysicsConfig(sleep_calm=sleep)) as projector:
            out[sleep] = projector.project_batch(starts)
    assert np.mean(out[True][1] == out[False][1]) >= 0.9
    both = (out[True][1] == STATUS_REST) & (out[False][1] == STATUS_REST)
    moved = np.linalg.norm(out[True][0][both, :, :3, 3] - out[False][0][both, :, :3, 3], axis=-1)
    assert both.sum() >= 20 and np.median(moved) < 0.5 * MM


def test_a_sunk_table_rests_objects_that_far_down_and_leaves_no_state():
    models = [box([0.06, 0.06, 0.06], 1), cylinder(obj_id=2)]
    scene = poses([0, 0, 0.04, 0, 0, 0], [0.1, 0, 0.07, 0, 0, 0])
    with PhysicsProjector(models, TABLE) as projector:
        flat, status, _ = projector.project(scene)
        sunk, sunk_status, _ = projector.project(scene, sink=0.008)
        again = projector.project(scene)
    assert status == sunk_status == STATUS_REST
    # The box's centre rests half its height above the surface, the cylinder's likewise: 8 mm lower when sunk.
    assert abs(flat[0, 2, 3] - 0.03) < 1 * MM and abs(flat[1, 2, 3] - 0.05) < 1 * MM
    assert np.allclose(sunk[:, 2, 3], flat[:, 2, 3] - 0.008, atol=1 * MM)
    assert np.array_equal(again[0], flat)
    with PhysicsProjector(models, TABLE) as projector:
        out, _, _ = projector.project_batch(np.stack([scene, scene]), np.array([0.0, 0.008]))
    assert np.array_equal(out[0], flat) and np.array_equal(out[1], sunk)


def test_batch_matches_single_particles():
    models = [box([0.06, 0.06, 0.06], 1), box([0.04, 0.08, 0.03], 2)]
    batch = np.stack([poses([0, 0, 0.05, 0, 0, 0], [0.03, 0, 0.03, 0, 0, 1]),
                      poses([0.1, 0, 0.03, 0.5, 0, 0], [0.1, 0.02, 0.1, 0, 0, 0])])
    with PhysicsProjector(models, TABLE) as projector:
        out, status, steps = projector.project_batch(batch)
        singles = [projector.project(T) for T in batch[::-1]][::-1]
    assert out.shape == batch.shape and status.dtype == np.int8 and steps.dtype == np.int32
    for i, (T, s, n) in enumerate(singles):
        assert np.array_equal(out[i], T) and status[i] == s and steps[i] == n


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_input_is_unstable_and_returned_unchanged(bad):
    start = poses([0, 0, 0.05, 0, 0, 0], [0.1, 0, 0.05, 0, 0, 0])
    start[1, 0, 3] = bad
    with PhysicsProjector([box([0.05] * 3, 1), box([0.05] * 3, 2)], TABLE) as projector:
        out, status, steps = projector.project(start)
        healthy = projector.project(poses([0, 0, 0.05, 0, 0, 0], [0.1, 0, 0.05, 0, 0, 0]))
    assert status == STATUS_UNSTABLE and steps == 0
    assert np.array_equal(out, start, equal_nan=True)
    assert healthy[1] == STATUS_REST


def test_non_rotation_and_far_away_inputs_are_unstable():
    with PhysicsProjector([box([0.05] * 3)], TABLE) as projector:
        squashed = poses([0, 0, 0.05, 0, 0, 0])
        squashed[0, :3, :3] *= 0.5
        far = poses([50.0, 0, 0.05, 0, 0, 0])
        for start in (squashed, far):
            out, status, _ = projector.project(start)
            assert status == STATUS_UNSTABLE and np.array_equal(out, start)


def test_blow_up_is_unstable_and_leaves_the_projector_clean():
    # With a 0.5 m/s speed limit, a 20 cm drop (2 m/s at impact) counts as a blow-up.
    config = PhysicsConfig(max_speed=0.5)
    models = [box([0.05] * 3)]
    start = poses([0, 0, 0.2, 0, 0, 0])
    calm = poses([0, 0, 0.026, 0.1, 0, 0])
    with PhysicsProjector(models, TABLE, config) as projector:
        out, status, steps = projector.project(start)
        after = projector.project(calm)
    with PhysicsProjector(models, TABLE, config) as fresh:
        alone = fresh.project(calm)
    assert status == STATUS_UNSTABLE and steps > 0 and np.array_equal(out, start)
    assert after[1] == STATUS_REST and np.array_equal(after[0], alone[0])


def test_step_cap_returns_the_poses_reached():
    with PhysicsProjector([box([0.05] * 3)], TABLE, PhysicsConfig(max_steps=10)) as projector:
        out, status, steps = projector.project(poses([0, 0, 0.3, 0, 0, 0]))
    assert status == STATUS_STEP_CAP and steps == 10
    assert np.all(np.isfinite(out)) and 0.2 < out[0, 2, 3] < 0.3  # falling, partway down


def test_wrong_shapes_and_settings_raise_input_error():
    with PhysicsProjector([box([0.05] * 3)], TABLE) as projector:
        with pytest.raises(InputError):
            projector.project(np.eye(4))
        with pytest.raises(InputError):
            projector.project_batch(np.eye(4)[None, None, None])
    with pytest.raises(InputError):
        PhysicsConfig(timestep=0.0)
    with pytest.raises(InputError):
        PhysicsConfig(off_table_z=0.1)


def test_collision_shape_kinds(cache_dir):
    shape = collision_shape_for(trimesh.creation.box(extents=[0.1, 0.06, 0.04]))
    assert shape.kind == "box"
    np.testing.assert_allclose(shape.half_extents, [0.05, 0.03, 0.02])
    np.testing.assert_array_equal(shape.T_obj_shape, np.eye(4))
    turned = trimesh.creation.box(extents=[0.1, 0.06, 0.04], transform=poses([0.01, 0, 0, 0.3, 0.5, 0.1])[0])
    shape = collision_shape_for(turned)
    assert shape.kind == "box"
    np.testing.assert_allclose(np.sort(shape.half_extents), [0.02, 0.03, 0.05], atol=1e-9)
    assert collision_shape_for(cylinder().mesh).kind == "cylinder"
    assert collision_shape_for(cylinder().mesh, kind="convex").kind == "convex"
    annulus = trimesh.creation.annulus(r_min=0.03, r_max=0.04, height=0.08)
    assert collision_shape_for(annulus, cache_dir=cache_dir).kind == "compound"
    assert collision_shape_for(cup_mesh(), cache_dir=cache_dir).kind == "compound"



def rounded_box(extents, radius) -> trimesh.Trimesh:
    """A box of ``extents`` with edges and corners rounded to ``radius``: the hull of spheres at the corners of
    the inner box (YCB's food boxes look like this)."""
    inner = np.asarray(extents) / 2 - radius
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    corners = np.array(np.meshgrid(*[[-1, 1]] * 3, indexing="ij")).reshape(3, -1).T * inner
    return trimesh.convex.convex_hull(np.concatenate([sphere.vertices + c for c in corners]))


def test_rounded_box_collides_as_a_box_and_rests_like_one():
    mesh = rounded_box([0.09, 0.05, 0.17], 0.006)
    turned = mesh.copy().apply_transform(poses([0.01, -0.02, 0.03, 0.2, -0.4, 0.7])[0])
    for m in (mesh, turned):
        shape = collision_shape_for(m)
        assert shape.kind == "box"
        np.testing.assert_allclose(np.sort(2 * shape.half_extents), [0.05, 0.09, 0.17], atol=2e-4)
        assert 0.9 < shape.fit_volume <= 1.0 and 0 < shape.fit_deviation < 3 * MM
    with PhysicsProjector([ObjectModel(1, turned)], TABLE) as projector:
        out, status, _ = projector.project(poses([0, 0, 0.2, 0.3, 0.1, 0]))
    assert status in (STATUS_REST, STATUS_STEP_CAP)
    lowest = np.min(turned.vertices @ out[0, :3, :3].T[:, 2] + out[0, 2, 3])
    assert abs(lowest) < 1 * MM  # on a face, touching the table


def test_cylinder_like_mesh_collides_as_a_cylinder():
    # A can: 24-sided, with a rim 2 mm proud of the body at top and bottom, axis along the mesh's x.
    profile = np.array([[0, 0], [0.033, 0], [0.033, 0.006], [0.031, 0.008], [0.031, 0.092], [0.033, 0.094],
                        [0.033, 0.1], [0, 0.1]])
    can = trimesh.creation.revolve(profile, sections=24)
    can.apply_transform(poses([0.0, 0.0, 0.0, 0.0, np.pi / 2, 0.0])[0])
    shape = collision_shape_for(can)
    assert shape.kind == "cylinder"
    axis = shape.T_obj_shape[:3, 2]
    assert abs(abs(axis[0]) - 1) < 1e-6  # Bullet's cylinder axis (its z) along the can's axis
    np.testing.assert_allclose(shape.half_extents, [0.033, 0.033, 0.05], atol=2e-4)
    model = ObjectModel(1, can)
    with PhysicsProjector([model], TABLE) as projector:
        # Standing on its end, it stays; lying on its side it rests there, rolling friction stops it rolling on.
        upright, s1, _ = projector.project(poses([0, 0, 0.0002, 0.0, -np.pi / 2, 0.0]))
        start = poses([0, 0, 0.04, 0.0, 0.0, 0.3])
        lying, s2, _ = projector.project(start)

    def lowest(T):
        return np.min(can.vertices @ T[:3, :3].T[:, 2] + T[2, 3])

    assert s1 == STATUS_REST and abs(lowest(upright[0])) < 1 * MM
    assert abs(upright[0, :3, 0] @ [0, 0, 1]) > 0.999  # axis vertical
    assert np.linalg.norm(upright[0, :2, 3]) < 1 * MM
    assert s2 == STATUS_REST and abs(lowest(lying[0])) < 2 * MM  # a line contact: Bullet lets it sink a little
    assert abs(lying[0, :3, 0] @ [0, 0, 1]) < 0.01  # on its side
    centre = [T[:3, :3] @ [0.05, 0, 0] + T[:3, 3] for T in (start[0], lying[0])]
    assert np.linalg.norm(centre[1][:2] - centre[0][:2]) < 0.02  # rolled no further than 2 cm


def test_collision_kind_override_and_fit_are_data():
    models = [cylinder(obj_id=7)]
    config = PhysicsConfig(shape_overrides=((7, "convex"),))
    with PhysicsProjector(models, TABLE, config) as projector:
        (shape,) = projector.shapes
    assert shape.kind == "convex" and len(shape.parts[0]) <= 64
    assert "convex" in shape.describe() and np.isfinite(shape.fit_volume) and np.isfinite(shape.fit_deviation)
    with pytest.raises(InputError):
        PhysicsConfig(shape_overrides=((7, "sphere"),))


def test_importing_physics_prints_nothing():
    # pybullet's C module prints its build time on import; every command's output would open with it.
    done = subprocess.run([sys.executable, "-c", "import workbench.physics, workbench.synth"], capture_output=True,
                          text=True, check=True)
    assert done.stdout == "" and done.stderr == ""
