"""How fast (and how well) the physics projection settles particles.

Scenes of 2 and 4 boxes (4-12 cm) on a table, started the way a particle filter would: upright or tumbled, some
dropped from a few cm, some sunk into the table or into each other, some stacked. Prints milliseconds per particle
(wall clock and this process's CPU time, which is steadier on a shared machine), steps, and the statuses.

    PYTHONPATH=. python benchmarks/physics_speed.py                      # 2 and 4 boxes, 200 particles each
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
from workbench.physics import STATUS_NAMES, PhysicsConfig, PhysicsProjector
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


def run(k: int, n: int, config: PhysicsConfig, accuracy: bool, seed: int) -> None:
    rng = np.random.default_rng(seed)
    models = box_models(rng, k)
    table = Table(-0.4, 0.4, -0.4, 0.4)
    starts = random_starts(rng, models, n)
    with PhysicsProjector(models, table, config) as projector:
        projector.project_batch(starts[:5])  # warm-up
        wall, cpu = time.perf_counter(), time.process_time()
        poses, status, steps = projector.project_batch(starts)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    counts = ", ".join(f"{STATUS_NAMES[s]} {np.sum(status == s)}" for s in STATUS_NAMES if np.any(status == s))
    print(f"{k} boxes, dt 1/{1 / config.timestep:.0f}: {1e3 * wall / n:.2f} ms/particle wall, "
          f"{1e3 * cpu / n:.2f} ms CPU; steps median {np.median(steps):.0f}, p90 {np.percentile(steps, 90):.0f}; "
          f"{counts}")
    if accuracy:
        strict = dataclasses.replace(config, max_steps=4 * config.max_steps, rest_linear=config.rest_linear / 10,
                                     rest_angular=config.rest_angular / 10, rest_checks=4 * config.rest_checks)
        with PhysicsProjector(models, table, strict) as projector:
            ref, ref_status, _ = projector.project_batch(starts)
        both = (status == 0) & (ref_status == 0)
        dt = np.linalg.norm(poses[both, :, :3, 3] - ref[both, :, :3, 3], axis=-1) * 1e3
        dr = np.degrees(rotation_angle(np.swapaxes(poses[both, :, :3, :3], -1, -2) @ ref[both, :, :3, :3]))
        print(f"  vs a stricter settle ({both.sum()} particles at rest in both): position median {np.median(dt):.2f} "
              f"mm, p95 {np.percentile(dt, 95):.2f} mm; rotation median {np.median(dr):.3f} deg, "
              f"p95 {np.percentile(dr, 95):.3f} deg")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", type=int, nargs="+", default=[2, 4])
    parser.add_argument("--particles", type=int, default=200)
    parser.add_argument("--timestep", type=float, default=PhysicsConfig.timestep)
    parser.add_argument("--max-steps", type=int, default=None)
    parser.add_argument("--accuracy", action="store_true")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    max_steps = args.max_steps or round(PhysicsConfig.max_steps * PhysicsConfig.timestep / args.timestep)
    config = PhysicsConfig(timestep=args.timestep, max_steps=max_steps)
    for k in args.objects:
        run(k, args.particles, config, args.accuracy, args.seed)


if __name__ == "__main__":
    main()
