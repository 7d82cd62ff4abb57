"""`workbench bench --speed [DATASET]`: particle evaluations per second and peak memory, on the first frame of
each scene of a BOP dataset, or without one on generated 2- and 4-object frames. Also each object's collision
shape with its measured fit, and the faces its render mesh keeps. Numbers, not assertions: docs/benchmarks.md quotes
them with the machine and the command."""

from __future__ import annotations

import os
import platform
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from workbench.evaluation import STAGES, make_evaluator
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator
from workbench.io import bop
from workbench.physics import PhysicsConfig, collision_shapes
from workbench.problem.build import load_bop_problem
from workbench.problem.problem import ProblemConfig
from workbench.render.depth import render_mesh
from workbench.synth import make_scenes


def machine_line() -> str:
    """The machine the figures were taken on, and its load at the end (another job would skew them)."""
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load "
            f"{os.getloadavg()[0]:.1f} at the end")


def _peak_rss_mb() -> tuple[float, float]:
    """(this process, largest finished child) peak resident memory in MB (Linux reports KiB)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return own, children


def measure(dataset: Path, scene_id: int, im_id: int, particles: int, workers: int, repeats: int,
            physics: PhysicsConfig = PhysicsConfig()) -> dict:
    """Times ``repeats`` full estimator iterations (after the random start) on one frame, simulated as ``physics``
    says -> figures."""
    _, problem = load_bop_problem(dataset, scene_id, im_id, config=ProblemConfig(physics=physics))
    # Chosen here once, so the workers find them in the cache; listed in the output.
    shapes = collision_shapes(problem.models, problem.config.physics)
    faces = [(len(m.mesh.faces), len(render_mesh(m.mesh, problem.config.render.max_depth_error).faces))
             for m in problem.models]
    evaluator = make_evaluator(problem, workers)
    try:
        estimator = Estimator(problem, EstimatorConfig(particles=particles, seed=0), evaluator)
        estimator.step()  # random start: includes worker warm-up, not timed
        walls, stage_sums, failed = [], dict.fromkeys((*STAGES, "resampling"), 0.0), 0
        before = estimator.evaluations
        for _ in range(repeats):
            t0 = time.perf_counter()
            report = estimator.step()
            walls.append(time.perf_counter() - t0)
            failed += report.n_failed
            for s in stage_sums:
                stage_sums[s] += report.timings[s]
        evaluated = estimator.evaluations - before  # the particles, and the sink's and the polish's scenes
    finally:
        evaluator.close()
    n = particles * repeats
    wall = float(np.median(walls))
    return {
        "frame": f"{scene_id}/{im_id}",
        "objects": problem.n_objects,
        "failed_pct": 100.0 * failed / n,
        "shapes": [f"obj {m.obj_id}: {s.describe()}, render {f} -> {r} faces"
                   for m, s, (f, r) in zip(problem.models, shapes, faces)],
        "render_px": problem.render_camera.width * problem.render_camera.height,
        "iteration_s": wall,
        "evals_per_s": evaluated / sum(walls),
        # Stage costs are CPU time summed over workers, per particle.
        **{f"{s}_ms": 1e3 * stage_sums[s] / n for s in stage_sums},
    }


def run_speed_benchmark(particles: int | None = None, workers: int = 2, repeats: int = 3,
                        dataset: Path | None = None, physics: str = PhysicsConfig.backend) -> list[dict]:
    """Measure the first frame of each scene of ``dataset`` (default: generated touching and four-box frames)
    with the simulator ``physics`` ("pybullet" or "mujoco") and print the table."""
    particles = particles or 1444
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        if dataset is None:
            dataset = Path(tmp) / "speed"
            make_scenes(dataset, ["touching", "four"], 1, seed=0)
        firsts: dict[int, int] = {}
        for scene_id, im_id in bop.list_frames(dataset):
            firsts.setdefault(scene_id, im_id)
        for scene_id, im_id in firsts.items():
            results.append(measure(dataset, scene_id, im_id, particles, workers, repeats,
                                   PhysicsConfig(backend=physics)))
    own, child = _peak_rss_mb()
    print(f"# workbench bench --speed {dataset}: N={particles}, {workers} workers, {repeats} timed iterations, "
          f"physics {physics}, {machine_line()}")
    print("| frame | objects | render px | iteration s | evaluations/s | failed % | projection ms | render ms "
          "| likelihood ms | resampling ms |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        print(f"| {r['frame']} | {r['objects']} | {r['render_px']} | {r['iteration_s']:.2f} | {r['evals_per_s']:.0f} "
              f"| {r['failed_pct']:.1f} | {r['projection_ms']:.3f} | {r['render_ms']:.3f} | {r['likelihood_ms']:.3f} "
              f"| {r['resampling_ms']:.3f} |")
    print(f"peak memory: main process {own:.0f} MB, largest worker {child:.0f} MB")
    for r in results:
        print(f"frame {r['frame']} geometry:")
        for line in r["shapes"]:
            print(f"  {line}")
    return results
