"""The MuJoCo physics projector with real MuJoCo and pybullet: resting poses against Bullet's on replayed hypotheses,
statuses, determinism, compound bodies, the backend setting and ``--physics`` on the command line."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from inbox import Inbox

from workbench.errors import InputError
from workbench.geometry import invert_pose, pose_from_xyz_rpy, rotation_angle
from workbench.physics import (
    STATUS_OFF_TABLE,
    STATUS_REST,
    STATUS_STEP_CAP,
    STATUS_UNSTABLE,
    PhysicsConfig,
    PhysicsProjector,
    make_projector,
)
from workbench.problem.scene import ObjectModel, Table

mujoco = pytest.importorskip("mujoco")
from workbench.physics import MujocoProjector  # noqa: E402  (after the skip: only meaningful with mujoco)

pytestmark = pytest.mark.slow  # needs pybullet and mujoco

TABLE = Table(-0.3, 0.3, -0.3, 0.3)
MM = 1e-3


def box(extents, obj_id=1) -> ObjectModel:
    return ObjectModel(obj_id, trimesh.creation.box(extents=extents))


def cup_mesh() -> trimesh.Trimesh:
    """A watertight cup 8 cm wide, 9 cm tall, 5 mm walls, standing on z = 0 in its own frame."""
    r, h, t = 0.04, 0.09, 0.005
    profile = np.array([[0, 0], [r, 0], [r, h], [r - t, h], [r - t, t], [0, t], [0, 0]])
    return trimesh.creation.revolve(profile, sections=32)


def poses(*xyz_rpy) -> np.ndarray:
    return pose_from_xyz_rpy(np.array(xyz_rpy, dtype=np.float64))


def tilt(T: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip(T[..., 2, 2], -1.0, 1.0))


def jittered(scene: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """A resting scene (K, 4, 4) and n - 1 hypotheses around it as the filter draws them: each object moved 1 cm
    (sd) sideways, lifted 0-3 cm or sunk up to 5 mm, turned 5 degrees (sd) about each axis. -> (n, K, 4, 4)."""
    K = len(scene)
    out = np.repeat(scene[None], n, axis=0)
    for i in range(1, n):
        out[i, :, :3, 3] += np.c_[rng.normal(0, 0.01, (K, 2)), rng.uniform(-0.005, 0.03, K)]
        turn = pose_from_xyz_rpy(np.c_[np.zeros((K, 3)), rng.normal(0, np.radians(5), (K, 3))])[:, :3, :3]
        out[i, :, :3, :3] = turn @ out[i, :, :3, :3]
    return out


def demo_case():
    """The bundled demo scene's objects at their true poses in the table frame, and hypotheses around them."""
    from workbench.cli import DEMO_DATASET
    from workbench.problem.build import load_bop_problem

    frame, problem = load_bop_problem(DEMO_DATASET, 0, 0)
    truth = invert_pose(problem.camera.T_cam_world) @ frame.gt_T_cam_obj
    return problem.models, problem.table, jittered(truth, 30, np.random.default_rng(0))


def stacked_case():
    """A 5 cm cube resting on a 20 x 15 x 5 cm slab, and hypotheses around that."""
    models = [box([0.2, 0.15, 0.05], 1), box([0.05, 0.05, 0.05], 2)]
    scene = poses([0, 0, 0.025, 0, 0, 0], [0.01, 0.01, 0.075, 0, 0, 0.4])
    return models, TABLE, jittered(scene, 20, np.random.default_rng(1))


def drops_case():
    """Three boxes of random sizes dropped upright from 0-3 cm at random places and headings."""
    rng = np.random.default_rng(2)
    models = [box(rng.uniform(0.04, 0.12, 3), k + 1) for k in range(3)]
    half = np.array([m.mesh.extents[2] / 2 for m in models])
    starts = np.stack([pose_from_xyz_rpy(np.c_[rng.uniform(-0.15, 0.15, (3, 2)), half + rng.uniform(0, 0.03, 3),
                                               np.zeros((3, 2)), rng.uniform(-np.pi, np.pi, 3)]) for _ in range(20)])
    return models, TABLE, starts


@pytest.mark.parametrize("case", [demo_case, stacked_case, drops_case])
def test_resting_poses_match_bullets_on_replayed_hypotheses(case):
    models, table, hypotheses = case()
    with PhysicsProjector(models, table) as bullet:
        expected, expected_status, _ = bullet.project_batch(hypotheses)
    with MujocoProjector(models, table) as projector:
        out, status, steps = projector.project_batch(hypotheses)
    assert np.all(expected_status == STATUS_REST) and np.all(status == STATUS_REST)
    assert np.all(steps < projector.config.max_steps)
    moved = np.linalg.norm(out[..., :3, 3] - expected[..., :3, 3], axis=-1)
    turned = rotation_angle(np.swapaxes(out[..., :3, :3], -1, -2) @ expected[..., :3, :3])
    assert np.median(moved) < 1 * MM, f"median {np.median(moved) / MM:.2f} mm from Bullet's"
    assert np.median(turned) < np.radians(1), f"median {np.degrees(np.median(turned)):.2f} degrees from Bullet's"


def test_box_overhanging_the_edge_falls_off():
    # Centre of mass 3 cm beyond the table's edge at x = 0.3.
    with MujocoProjector([box([0.1, 0.06, 0.04])], TABLE) as projector:
        out, status, _ = projector.project(poses([0.33, 0, 0.02, 0, 0, 0]))
    assert status == STATUS_OFF_TABLE
    assert out[0, 2, 3] < projector.config.off_table_z


def test_a_batch_is_deterministic_and_each_particle_independent_of_the_ones_before():
    models, table, hypotheses = stacked_case()
    with MujocoProjector(models, table) as projector:
        out, status, steps = projector.project_batch(hypotheses)
        again = projector.project_batch(hypotheses[::-1])
    with MujocoProjector(models, table) as fresh:
        alone = fresh.project(hypotheses[5])
    assert np.array_equal(again[0][::-1], out) and np.array_equal(again[1][::-1], status)
    assert np.array_equal(again[2][::-1], steps)
    assert np.array_equal(alone[0], out[5]) and alone[1:] == (status[5], steps[5])


def test_interpenetrating_boxes_are_pushed_apart_not_launched():
    # Two 6 cm cubes overlapping by 2 cm sideways, the second also sunk 1.5 cm into the table.
    models = [box([0.06, 0.06, 0.06], 1), box([0.06, 0.06, 0.06], 2)]
    start = poses([0.0, 0, 0.03, 0, 0, 0], [0.04, 0, 0.015, 0, 0, 0])
    with MujocoProjector(models, TABLE) as projector:
        out, status, _ = projector.project(start)
    assert status == STATUS_REST
    np.testing.assert_allclose(out[:, 2, 3], 0.03, atol=2 * MM)
    assert np.all(tilt(out) < np.radians(2))
    assert out[1, 0, 3] - out[0, 0, 3] > 0.06 - 2 * MM
    moved = np.linalg.norm(out[:, :2, 3] - start[:, :2, 3], axis=1)
    np.testing.assert_allclose(moved, 0.01, atol=3 * MM)  # half the overlap each


def test_cup_collides_as_its_convex_parts(tmp_path):
    # A cup (V-HACD parts: one geom each) with a 2 cm cube dropped into it rests with the cube inside, on its floor:
    # as one convex hull the cube would rest on the rim, 9 cm up.
    models = [ObjectModel(3, cup_mesh()), box([0.02, 0.02, 0.02], 4)]
    with MujocoProjector(models, TABLE, cache_dir=tmp_path) as projector:
        out, status, _ = projector.project(poses([0, 0, 0.002, 0, 0, 0], [0, 0, 0.1, 0, 0, 0.3]))
        assert projector.shapes[0].kind == "compound"
    assert status == STATUS_REST
    assert tilt(out[0]) < np.radians(2) and abs(out[0, 2, 3]) < 2 * MM
    assert out[1, 2, 3] < 0.03  # on the 5 mm floor, its centre 1.5-2 cm up (pieces padded as Bullet's), not the rim


def test_a_compound_rests_as_high_as_in_bullet(tmp_path):
    # Bullet pads a compound's pieces by 1 mm (pybullet's default margin): MuJoCo pads them as much.
    models = [ObjectModel(3, cup_mesh())]
    start = poses([0, 0, 0.005, 0, 0, 0])
    with PhysicsProjector(models, TABLE, cache_dir=tmp_path) as bullet:
        expected, _, _ = bullet.project(start)
    with MujocoProjector(models, TABLE, cache_dir=tmp_path) as projector:
        out, status, _ = projector.project(start)
    assert status == STATUS_REST
    assert abs(out[0, 2, 3] - expected[0, 2, 3]) < 0.3 * MM


def test_a_sleeping_body_is_woken_when_something_falls_on_it():
    # As Bullet's (tests/test_physics.py): a 3 cm cube at rest from the start falls asleep; a 20 cm board standing on
    # its edge, tilted towards it, topples onto it later and shoves it, as if the cube had never slept.
    models = [box([0.03, 0.03, 0.03], 1), box([0.06, 0.06, 0.2], 2)]
    lean = 0.4
    start = poses([0, 0, 0.015, 0, 0, 0], [-0.12, 0, 0.1 * np.cos(lean) + 0.03 * np.sin(lean) + 0.002, 0, lean, 0])
    with MujocoProjector(models, TABLE) as projector:
        out, status, _ = projector.project(start)
    with MujocoProjector(models, TABLE, PhysicsConfig(sleep_calm=False)) as projector:
        awake, _, _ = projector.project(start)
    assert status == STATUS_REST
    assert np.linalg.norm(out[0, :3, 3] - start[0, :3, 3]) > 1 * MM  # a cube left asleep would not move at all
    assert tilt(out[1]) < np.radians(85)  # the board rests propped on it
    assert np.max(np.linalg.norm(out[:, :3, 3] - awake[:, :3, 3], axis=1)) < 1 * MM


def test_calm_bodies_sleep_as_in_bullet():
    # A cube balanced on one edge, 1 degree off its tipping point, is calm at first and starts tipping slowly, while
    # a second cube dropped from 30 cm keeps the simulation going: Bullet's projector freezes the calm one, and so
    # does MuJoCo's sleeping; awake in MuJoCo, it falls onto a face.
    models = [box([0.05, 0.05, 0.05], 1), box([0.05, 0.05, 0.05], 2)]
    start = poses([0, 0, 0.025 * np.sqrt(2), np.radians(44), 0, 0], [0.15, 0, 0.3, 0, 0, 0])
    with PhysicsProjector(models, TABLE) as bullet:
        expected, expected_status, _ = bullet.project(start)
    with MujocoProjector(models, TABLE) as projector:
        out, status, _ = projector.project(start)
    with MujocoProjector(models, TABLE, PhysicsConfig(sleep_calm=False)) as awake:
        fallen, fallen_status, _ = awake.project(start)
    assert expected_status == status == fallen_status == STATUS_REST
    assert tilt(expected[0]) > np.radians(40) and tilt(out[0]) > np.radians(40)  # frozen on its edge
    assert np.linalg.norm(out[0, :3, 3] - expected[0, :3, 3]) < 1 * MM
    assert abs(fallen[0, 2, 3] - 0.025) < 1 * MM  # awake: lying on a face


def test_a_sunk_table_rests_objects_that_far_down():
    models = [box([0.06, 0.06, 0.06], 1)]
    scene = poses([0, 0, 0.04, 0, 0, 0])
    with MujocoProjector(models, TABLE) as projector:
        out, status, _ = projector.project_batch(np.stack([scene, scene, scene]), np.array([0.0, 0.008, 0.0]))
    assert np.all(status == STATUS_REST)
    assert abs(out[0, 0, 2, 3] - 0.03) < 1 * MM
    assert abs(out[1, 0, 2, 3] - (0.03 - 0.008)) < 1 * MM
    assert np.array_equal(out[2], out[0])


def test_bad_inputs_are_unstable_and_returned_unchanged_and_the_step_cap_holds():
    with MujocoProjector([box([0.05] * 3)], TABLE) as projector:
        squashed = poses([0, 0, 0.05, 0, 0, 0])
        squashed[0, :3, :3] *= 0.5
        far = poses([50.0, 0, 0.05, 0, 0, 0])
        nan = poses([0, 0, 0.05, 0, 0, 0])
        nan[0, 0, 3] = np.nan
        for start in (squashed, far, nan):
            out, status, steps = projector.project(start)
            assert status == STATUS_UNSTABLE and steps == 0 and np.array_equal(out, start, equal_nan=True)
        with pytest.raises(InputError):
            projector.project(np.eye(4))
    with MujocoProjector([box([0.05] * 3)], TABLE, PhysicsConfig(max_steps=10)) as projector:
        out, status, steps = projector.project(poses([0, 0, 0.3, 0, 0, 0]))
    assert status == STATUS_STEP_CAP and steps == 10 and 0.2 < out[0, 2, 3] < 0.3
    with MujocoProjector([box([0.05] * 3)], TABLE, PhysicsConfig(max_speed=0.5)) as projector:
        out, status, steps = projector.project(poses([0, 0, 0.2, 0, 0, 0]))  # 2 m/s at impact: a blow-up here
    assert status == STATUS_UNSTABLE and steps > 0


def test_make_projector_builds_the_backend_the_config_names():
    models = [box([0.05] * 3)]
    with make_projector(models, TABLE, PhysicsConfig(backend="mujoco")) as projector:
        assert isinstance(projector, MujocoProjector)
    with make_projector(models, TABLE) as projector:
        assert isinstance(projector, PhysicsProjector)
    with pytest.raises(InputError, match="backend"):
        PhysicsConfig(backend="havok")


def test_estimate_runs_on_the_demo_with_mujoco(tmp_path):
    from workbench.cli import DEMO_DATASET, build_parser, main, problem_config

    out = tmp_path / "results.csv"
    argv = ["estimate", str(DEMO_DATASET), "--physics", "mujoco", "--particles", "8", "--iterations", "2",
            "--workers", "1", "--max-render-pixels", "2000", "--no-settle", "--out", str(out)]
    assert problem_config(build_parser().parse_args(argv)).physics.backend == "mujoco"  # what the workers get
    assert main(argv) == 0
    rows = out.read_text().strip().splitlines()[1:]
    assert len(rows) == 2  # the demo's two objects


def test_a_bad_physics_backend_is_refused(capsys):
    from workbench.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["estimate", "assets/demo", "--physics", "havok"])
    assert exit_.value.code == 2
    assert "--physics" in capsys.readouterr().err


def test_the_workbench_engine_simulates_in_mujoco_and_its_sessions_say_so(tmp_path):
    import json
    import shutil

    from workbench.app import protocol as p
    from workbench.app.engine.engine import DEMO_DIR, Engine
    from workbench.inference.config import EstimatorConfig

    dataset = tmp_path / "demo"
    shutil.copytree(DEMO_DIR, dataset)
    inbox = Inbox()
    engine = Engine(inbox, workers=1, physics=PhysicsConfig(backend="mujoco"))  # as `serve --physics mujoco`
    try:
        engine.handle(p.Load(p.Source(dataset=dataset, scene_id=0, im_id=0), EstimatorConfig(particles=8), "robust"))
        engine.step()
        engine.handle(p.SaveSession(tmp_path / "sessions", "s"))
    finally:
        engine.close()
    assert not [m for m in inbox if isinstance(m, p.Failure)]
    assert engine.problem.config.physics.backend == "mujoco"
    saved = json.loads((tmp_path / "sessions" / "s.json").read_text())
    assert saved["problem_config"]["physics"]["backend"] == "mujoco"


def test_bench_speed_measures_mujoco(touching_dataset, capsys):
    from workbench.cli import main

    assert main(["bench", "--speed", str(touching_dataset), "--particles", "16", "--repeats", "1", "--workers", "1",
                 "--physics", "mujoco"]) == 0
    out = capsys.readouterr().out
    assert "physics mujoco" in out
    rows = [line for line in out.splitlines() if line.startswith("| ") and "frame" not in line]
    assert len(rows) == 1 and float(rows[0].split("|")[5]) > 0  # evaluations/s measured
