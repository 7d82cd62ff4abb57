"""`workbench bench --speed`: particle evaluations per second and peak memory, on generated 2- and 4-object
frames. Numbers, not assertions: the README quotes them with the machine and the command."""

from __future__ import annotations

import os
import platform
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from workbench import bop
from workbench.estimators import Estimator, EstimatorConfig
from workbench.evaluation import STAGES, make_evaluator
from workbench.pipeline import load_bop_problem
from workbench.synth import make_scenes


def _peak_rss_mb() -> tuple[float, float]:
    """(this process, largest finished child) peak resident memory in MB (Linux reports KiB)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return own, children


def measure(dataset: Path, scene_id: int, particles: int, workers: int, repeats: int) -> dict:
    """Times ``repeats`` full estimator iterations (after the random start) on one frame -> figures."""
    _, problem = load_bop_problem(dataset, scene_id, 0)
    evaluator = make_evaluator(problem, workers)
    try:
        estimator = Estimator(problem, EstimatorConfig(particles=particles, seed=0), evaluator)
        estimator.step()  # random start: includes worker warm-up, not timed
        walls, stage_sums = [], dict.fromkeys((*STAGES, "resampling"), 0.0)
        for _ in range(repeats):
            t0 = time.perf_counter()
            report = estimator.step()
            walls.append(time.perf_counter() - t0)
            for s in stage_sums:
                stage_sums[s] += report.timings[s]
    finally:
        evaluator.close()
    n = particles * repeats
    wall = float(np.median(walls))
    return {
        "objects": problem.n_objects,
        "render_px": problem.render_camera.width * problem.render_camera.height,
        "iteration_s": wall,
        "evals_per_s": particles / wall,
        # Stage costs are CPU time summed over workers, per particle.
        **{f"{s}_ms": 1e3 * stage_sums[s] / n for s in stage_sums},
    }


def run_speed_benchmark(particles: int | None = None, workers: int = 2, repeats: int = 3) -> list[dict]:
    particles = particles or 1444
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        dataset = Path(tmp) / "speed"
        make_scenes(dataset, ["touching", "four"], 1, seed=0)
        for scene_id, _ in bop.list_frames(dataset):
            results.append(measure(dataset, scene_id, particles, workers, repeats))
    own, child = _peak_rss_mb()
    print(f"# workbench bench --speed: N={particles}, {workers} workers, {repeats} timed iterations, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs")
    print("| objects | render px | iteration s | evaluations/s | projection ms | render ms | likelihood ms | resampling ms |")
    print("|---|---|---|---|---|---|---|---|")
    for r in results:
        print(f"| {r['objects']} | {r['render_px']} | {r['iteration_s']:.2f} | {r['evals_per_s']:.0f} | "
              f"{r['projection_ms']:.3f} | {r['render_ms']:.3f} | {r['likelihood_ms']:.3f} | {r['resampling_ms']:.3f} |")
    print(f"peak memory: main process {own:.0f} MB, largest worker {child:.0f} MB")
    return results
