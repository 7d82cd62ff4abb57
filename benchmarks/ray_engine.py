"""`--engine local` against `--engine ray` (a Ray instance started on this machine) on a small generated suite:
wall time, Ray's start-up cost, and the scaling from 1 to 2 CPUs.

    PYTHONPATH=. .venv/bin/python benchmarks/ray_engine.py                  # 6 frames, 48 particles x 8 iterations
    PYTHONPATH=. .venv/bin/python benchmarks/ray_engine.py --per-category 2 --particles 32 --json out.json

Each engine estimates the same frames with the same settings (early stop off, so every frame costs its full
budget) and, as the tests check, writes the same poses. Measured:
- local: frames one after another, each on a pool of 2 worker processes started for it (what `estimate` does);
- Ray, 2 CPUs and 1 CPU: ``ray.init`` (a Ray instance of that many CPUs on this machine), then the frames twice:
  cold (Ray starts its worker processes, each importing pybullet, pyrender and open3d once) and warm (the same
  workers reused). Start-up cost: ``ray.init`` plus cold minus warm. Overhead: wall time x CPUs against the frame
  tasks' time (summed, from their own clocks).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from workbench.bench.tables import machine
from workbench.evaluation.ray import RayConfig, connect, disconnect
from workbench.inference.config import EstimatorConfig
from workbench.problem.problem import ProblemConfig
from workbench.run.runner import estimate_frames
from workbench.synth import make_scenes


def load() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def timed(fn) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def frame_seconds(rows) -> list[float]:
    """Per frame: the time column of its rows (the frame's wall seconds, measured where it ran)."""
    return list({(r.scene_id, r.im_id): r.time for r in rows}.values())


def run_on_ray(dataset: Path, frames, config: EstimatorConfig, cpus: int) -> dict:
    """Start a Ray instance of ``cpus`` CPUs, run the frames twice on it (cold: Ray starts its worker processes;
    warm: it reuses them), stop it -> seconds and overheads."""
    init_s, _ = timed(lambda: connect(RayConfig(num_cpus=cpus)))
    out = {"cpus": cpus, "init_s": init_s}
    try:
        for run in ("cold", "warm"):
            wall_s, rows = timed(lambda: estimate_frames(dataset, frames, config, ProblemConfig(), 2,
                                                         early_stop=False, ray=RayConfig(num_cpus=cpus)))
            tasks = frame_seconds(rows)
            out[run] = {"wall_s": wall_s, "task_s_sum": sum(tasks), "task_s_median": statistics.median(tasks),
                        # Wall time x CPUs against the frames' own time: scheduling, transfers, idle CPUs.
                        "overhead_vs_tasks": wall_s * cpus / sum(tasks) - 1}
    finally:
        disconnect()
    # What a run pays once: starting Ray, and its worker processes' start (imports) during the first frames.
    out["startup_s"] = init_s + out["cold"]["wall_s"] - out["warm"]["wall_s"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--categories", default="touching,stacked")
    ap.add_argument("--per-category", type=int, default=3)
    ap.add_argument("--particles", type=int, default=48)
    ap.add_argument("--iterations", type=int, default=8)
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        dataset = Path(tmp) / "suite"
        make_scenes(dataset, args.categories.split(","), args.per_category, seed=0)
        frames = [(s, 0) for s in range(len(args.categories.split(",")) * args.per_category)]
        # Early stop off (below): every frame costs its full budget whichever engine runs it.
        config = EstimatorConfig(particles=args.particles, iterations=args.iterations, seed=0)
        load_before = load()
        # The collision-shape and render-mesh caches are filled once here, so that no engine pays for them.
        os.environ["XDG_CACHE_HOME"] = str(Path(tmp) / "cache")
        estimate_frames(dataset, frames, EstimatorConfig(particles=4, iterations=0), ProblemConfig(), 1)
        local_s, local_rows = timed(lambda: estimate_frames(dataset, frames, config, ProblemConfig(), 2,
                                                            early_stop=False))
        ray2 = run_on_ray(dataset, frames, config, 2)
        ray1 = run_on_ray(dataset, frames, config, 1)
        load_after = load()

    local_tasks = frame_seconds(local_rows)
    result = {
        "machine": machine(), "load_before": load_before, "load_after": load_after, "frames": len(frames),
        "particles": args.particles, "iterations": args.iterations, "workers": 2,
        "local": {"wall_s": local_s, "frame_s_median": statistics.median(local_tasks)},
        "ray_2cpu": ray2, "ray_1cpu": ray1,
        # The whole Ray run as a user sees it (start-up included) against the local engine's.
        "ray_vs_local": (ray2["init_s"] + ray2["cold"]["wall_s"]) / local_s - 1,
        "speedup_1_to_2_cpus": ray1["warm"]["wall_s"] / ray2["warm"]["wall_s"],
    }
    print(json.dumps(result, indent=1))
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
