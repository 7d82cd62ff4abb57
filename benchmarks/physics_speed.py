"""How fast (and how well) the physics projection settles particles, in Bullet and in MuJoCo.

Scenes of 2 and 4 boxes (4-12 cm) on a table, started the way a particle filter would: upright or tumbled, some
dropped from a few cm, some sunk into the table or into each other, some stacked. Prints, per backend, milliseconds
per particle (wall clock and this process's CPU time, which is steadier on a shared machine), steps, and the
statuses; with both backends, how far MuJoCo's resting poses are from Bullet's on the same starts.

    PYTHONPATH=. python benchmarks/physics_speed.py                      # 2 and 4 boxes, 200 particles, both backends
    PYTHONPATH=. python benchmarks/physics_speed.py --backends pybullet  # Bullet only (MuJoCo not installed)
    PYTHONPATH=. python benchmarks/physics_speed.py --timestep 0.001333  # the paper's 750 steps/s
    PYTHONPATH=. python benchmarks/physics_speed.py --accuracy           # also: distance to a stricter settle
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
import trimesh

from workbench.geometry import pose_from_xyz_rpy, rotation_angle
from workbench.physics import BACKENDS, STATUS_NAMES, STATUS_REST, PhysicsConfig, make_projector
from workbench.problem.scene import ObjectModel, Table


def box_models(rng: np.random.Generator, k: int) -> list[ObjectModel]:
    return [ObjectModel(i + 1, trimesh.creation.box(extents=rng.uniform(0.04, 0.12, size=3))) for i in range(k)]


def random_starts(rng: np.random.Generator, models: list[ObjectModel], n: int) -> np.ndarray:
    """Plausible-ish hypotheses (n, K, 4, 4): 60 % upright with a random yaw, the rest tumbled; heights from 2 cm
    sunk to 3 cm above resting; every third particle stacks object 1 on object 0."""
    K = len(models)
    half = np.array([m.mesh.extents / 2 for m in models])
    out = np.empty((n, K, 4, 4))
    for i in range(n):
        xyz_rpy = np.zeros((K, 6))
        xyz_rpy[:, :2] = rng.uniform(-0.08, 0.08, size=(K, 2))
        xyz_rpy[:, 5] = rng.uniform(-np.pi, np.pi, size=K)
        tumbled = rng.random(K) > 0.6
        xyz_rpy[tumbled, 3:5] = rng.uniform(-np.pi, np.pi, size=(int(tumbled.sum()), 2))
        xyz_rpy[:, 2] = half[:, 2] + rng.uniform(-0.02, 0.03, size=K)
        if i % 3 == 0 and K > 1:
            xyz_rpy[1, :2] = xyz_rpy[0, :2] + rng.uniform(-0.01, 0.01, size=2)
            xyz_rpy[1, 2] = xyz_rpy[0, 2] + half[0, 2] + half[1, 2] + rng.uniform(-0.01, 0.01)
        out[i] = pose_from_xyz_rpy(xyz_rpy)
    return out


def settle(models, table, config: PhysicsConfig, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Settle ``starts`` (n, K, 4, 4) in ``config.backend`` -> (resting poses, statuses, ms per particle wall, CPU).
    The first 5 are settled once before timing (warm-up)."""
    with make_projector(models, table, config) as projector:
        projector.project_batch(starts[:5])
        wall, cpu = time.perf_counter(), time.process_time()
        poses, status, steps = projector.project_batch(starts)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    counts = ", ".join(f"{STATUS_NAMES[s]} {np.sum(status == s)}" for s in STATUS_NAMES if np.any(status == s))
    print(f"  {config.backend}: {1e3 * wall / len(starts):.2f} ms/particle wall, {1e3 * cpu / len(starts):.2f} ms CPU; "
          f"steps median {np.median(steps):.0f}, p90 {np.percentile(steps, 90):.0f}; {counts}")
    return poses, status, 1e3 * wall / len(starts), 1e3 * cpu / len(starts)


def apart(a: np.ndarray, a_status: np.ndarray, b: np.ndarray, b_status: np.ndarray) -> str:
    """How far two sets of resting scenes (n, K, 4, 4) are, over the particles at rest in both: object positions
    (mm) and rotations (degrees), median and p90."""
    both = (a_status == STATUS_REST) & (b_status == STATUS_REST)
    dt = np.linalg.norm(a[both, :, :3, 3] - b[both, :, :3, 3], axis=-1) * 1e3
    dr = np.degrees(rotation_angle(np.swapaxes(a[both, :, :3, :3], -1, -2) @ b[both, :, :3, :3]))
    return (f"{both.sum()} particles at rest in both: position median {np.median(dt):.2f} mm, p90 "
            f"{np.percentile(dt, 90):.2f} mm; rotation median {np.median(dr):.3f} deg, "
            f"p90 {np.percentile(dr, 90):.3f} deg")


def run(k: int, n: int, config: PhysicsConfig, backends: list[str], accuracy: bool, seed: int) -> None:
    rng = np.random.default_rng(seed)
    models = box_models(rng, k)
    table = Table(-0.4, 0.4, -0.4, 0.4)
    starts = random_starts(rng, models, n)
    print(f"{k} boxes, {n} particles, dt 1/{1 / config.timestep:.0f}:")
    settled = {}
    for backend in backends:
        cfg = dataclasses.replace(config, backend=backend)
        poses, status, _, _ = settle(models, table, cfg, starts)
        settled[backend] = poses, status
        if accuracy:
            strict = dataclasses.replace(cfg, max_steps=4 * cfg.max_steps, rest_linear=cfg.rest_linear / 10,
                                         rest_angular=cfg.rest_angular / 10, rest_checks=4 * cfg.rest_checks)
            with make_projector(models, table, strict) as projector:
                ref, ref_status, _ = projector.project_batch(starts)
            print(f"    vs a stricter settle in {backend}: {apart(poses, status, ref, ref_status)}")
    if len(settled) == 2:
        print(f"  mujoco vs pybullet: {apart(*settled['mujoco'], *settled['pybullet'])}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", type=int, nargs="+", default=[2, 4])
    parser.add_argument("--particles", type=int, default=200)
    parser.add_argument("--timestep", type=float, default=PhysicsConfig.timestep)
    parser.add_argument("--max-steps", type=int, default=None)
    parser.add_argument("--backends", nargs="+", choices=BACKENDS, default=list(BACKENDS))
    parser.add_argument("--accuracy", action="store_true")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    max_steps = args.max_steps or round(PhysicsConfig.max_steps * PhysicsConfig.timestep / args.timestep)
    config = PhysicsConfig(timestep=args.timestep, max_steps=max_steps)
    for k in args.objects:
        run(k, args.particles, config, args.backends, args.accuracy, args.seed)


if __name__ == "__main__":
    main()
