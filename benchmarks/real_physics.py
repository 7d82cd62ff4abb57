"""Physics projection on real meshes: cost per particle and resting poses, per collision shape kind and setting.

Hypotheses are those a filter really evaluates: the random start and the first diffusion iterations of PI-PF on
the first frame of each scene of a BOP dataset. Each setting projects the same sample of them and is compared with
the reference: the unsimplified shapes (every object the convex hull of all its vertices, concave ones fine V-HACD
pieces) at the default settings. Prints CPU ms per particle, steps (median, p90), statuses, and how far the
resting poses are from the reference's (mean model-point distance per object, median and p90, over the particles
at rest in both). Setting "mujoco" is the default settings in MuJoCo (``--physics mujoco``); when it runs, its
distance to Bullet's resting poses (the chosen shapes, default settings) is printed too.

    PYTHONPATH=. python benchmarks/real_physics.py ../shared/datasets/ycbv-real-dev
    PYTHONPATH=. python benchmarks/real_physics.py ../shared/datasets/ycbv-real-dev --settings default mujoco
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from workbench.evaluation import LocalEvaluator
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator
from workbench.io import bop
from workbench.physics import STATUS_NAMES, STATUS_REST, STATUS_STEP_CAP, PhysicsConfig, make_projector
from workbench.physics.collision import collision_shape_for
from workbench.problem.build import load_bop_problem
from workbench.score.metrics import model_points


class RecordingEvaluator(LocalEvaluator):
    """A LocalEvaluator that keeps every batch of hypotheses it is given."""

    def __init__(self, problem):
        super().__init__(problem)
        self.batches: list[np.ndarray] = []

    def evaluate(self, hypotheses, sink=None, project=True):
        if project:  # the batches physics projects
            self.batches.append(np.array(hypotheses))
        return super().evaluate(hypotheses, sink, project)


def filter_hypotheses(problem, particles: int, iterations: int, seed: int) -> np.ndarray:
    """The hypotheses PI-PF evaluates in its first ``iterations`` -> (iterations * particles, K, 4, 4)."""
    evaluator = RecordingEvaluator(problem)
    try:
        estimator = Estimator(problem, EstimatorConfig(particles=particles, seed=seed), evaluator)
        for _ in range(iterations):
            estimator.step()
    finally:
        evaluator.close()
    return np.concatenate(evaluator.batches)


def project(models, table, config, shapes, hypotheses):
    with make_projector(models, table, config, shapes=shapes) as projector:
        projector.project_batch(hypotheses[:3])  # warm-up
        cpu = time.process_time()
        rest, status, steps = projector.project_batch(hypotheses)
        cpu = time.process_time() - cpu
    return rest, status, steps, 1e3 * cpu / len(hypotheses)


def distances(a: np.ndarray, b: np.ndarray, points: list[np.ndarray]) -> np.ndarray:
    """Mean model-point distance (m) per particle and object between (B, K, 4, 4) scenes -> (B, K)."""
    out = np.empty(a.shape[:2])
    for k, p in enumerate(points):
        pa = p @ np.swapaxes(a[:, k, :3, :3], 1, 2) + a[:, k, None, :3, 3]
        pb = p @ np.swapaxes(b[:, k, :3, :3], 1, 2) + b[:, k, None, :3, 3]
        out[:, k] = np.linalg.norm(pa - pb, axis=-1).mean(axis=-1)
    return out


def settled_apart(a, a_status, b, b_status, points: list[np.ndarray]) -> np.ndarray:
    """Mean model-point distances (mm) per object between two projections of the same hypotheses (B, K, 4, 4),
    over the particles at rest (or at the step cap) in both -> (n * K,)."""
    ok = np.isin(a_status, (STATUS_REST, STATUS_STEP_CAP)) & np.isin(b_status, (STATUS_REST, STATUS_STEP_CAP))
    return distances(a[ok], b[ok], points).ravel() * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--particles", type=int, default=150, help="per filter iteration")
    parser.add_argument("--iterations", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scenes", type=int, nargs="+", default=None, help="only these scene ids")
    parser.add_argument("--settings", nargs="+", default=None, help="only these settings (names as printed)")
    args = parser.parse_args()
    base = PhysicsConfig()
    settings = {
        "default": base,
        "max_steps 150": dataclasses.replace(base, max_steps=150),
        "max_steps 600": dataclasses.replace(base, max_steps=600),
        "rest 2x looser": dataclasses.replace(base, rest_linear=2 * base.rest_linear,
                                              rest_angular=2 * base.rest_angular),
        "rest 2x stricter": dataclasses.replace(base, rest_linear=base.rest_linear / 2,
                                                rest_angular=base.rest_angular / 2),
        "no rolling friction": dataclasses.replace(base, rolling_friction=0.0, spinning_friction=0.0),
        "solver 15 iterations": dataclasses.replace(base, solver_iterations=15),
        "dt 1/60, 150 steps": dataclasses.replace(base, timestep=1 / 60, max_steps=150),
        "check every 2": dataclasses.replace(base, check_every=2),
        "residual 1e-7 (Bullet's)": dataclasses.replace(base, solver_residual=1e-7),
        "pyramid friction": dataclasses.replace(base, cone_friction=False),
        "damping 0.5": dataclasses.replace(base, linear_damping=0.5, angular_damping=0.5),
        "calm bodies awake": dataclasses.replace(base, sleep_calm=False),
        "mujoco": dataclasses.replace(base, backend="mujoco"),
    }
    firsts: dict[int, int] = {}
    for scene_id, im_id in bop.list_frames(args.dataset):
        firsts.setdefault(scene_id, im_id)
    if args.settings:
        settings = {k: v for k, v in settings.items() if k in args.settings}
    for scene_id, im_id in firsts.items():
        if args.scenes and scene_id not in args.scenes:
            continue
        _, problem = load_bop_problem(args.dataset, scene_id, im_id)
        models, table = problem.models, problem.table
        hypotheses = filter_hypotheses(problem, args.particles, args.iterations, args.seed)
        points = [model_points(m.mesh, 300) for m in models]
        chosen = [collision_shape_for(m.mesh) for m in models]
        reference = [collision_shape_for(m.mesh, kind="reference") for m in models]
        hull = [collision_shape_for(m.mesh, kind="convex") for m in models]
        ref, ref_status, _, ref_ms = project(models, table, base, reference, hypotheses)
        print(f"\n## scene {scene_id} frame {im_id}: {len(models)} objects, {len(hypotheses)} hypotheses of PI-PF's "
              f"first {args.iterations} iterations")
        print("shapes: " + "; ".join(f"obj {m.obj_id} {s.describe()}" for m, s in zip(models, chosen)))
        print("| shapes | setting | CPU ms/particle | steps median | steps p90 | statuses | vs reference median mm "
              "| p90 mm |")
        print("|---|---|---|---|---|---|---|---|")
        runs = [("reference", "default", reference, base), ("hulls <= 64 v", "default", hull, base)]
        runs += [("chosen", name, chosen, cfg) for name, cfg in settings.items()]
        settled = {}
        for shape_name, setting, shapes, cfg in runs:
            rest, status, steps, ms = project(models, table, cfg, shapes, hypotheses)
            settled[shape_name, setting] = rest, status
            d = settled_apart(rest, status, ref, ref_status, points)
            counts = ", ".join(f"{STATUS_NAMES[s]} {np.mean(status == s) * 100:.0f} %" for s in STATUS_NAMES
                               if np.any(status == s))
            print(f"| {shape_name} | {setting} | {ms:.2f} | {np.median(steps):.0f} | {np.percentile(steps, 90):.0f} "
                  f"| {counts} | {np.median(d):.1f} | {np.percentile(d, 90):.1f} |")
        if ("chosen", "mujoco") in settled and ("chosen", "default") in settled:
            d = settled_apart(*settled["chosen", "mujoco"], *settled["chosen", "default"], points)
            print(f"MuJoCo vs Bullet (chosen shapes, default settings): median {np.median(d):.1f} mm, p90 "
                  f"{np.percentile(d, 90):.1f} mm (mean model-point distance per object)")


if __name__ == "__main__":
    main()
