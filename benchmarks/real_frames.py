"""Accuracy and wall time of the estimator on real BOP frames with ground truth (e.g. the YCB-Video dev set in
../shared/datasets/ycbv-real-dev): per frame, objects right (within 2 cm and 10 degrees, symmetry-aware), the
estimate's log-likelihood against the true scene's (projected by our physics, and as annotated), how far physics
moves the true scene, evaluations used and seconds; per object, how much the estimate gains when only that object
is put at its true pose (a gain: the search missed it; a loss: the likelihood prefers the estimate's pose), how far
settling moved it from the search's projected estimate, how far physics moves the settled scene, and its near ties
(``Estimator.ties``: turns the depth scores within the turn margin).

    .venv/bin/python benchmarks/real_frames.py ../shared/datasets/ycbv-real-dev [--proposals default|paper]
        [--method pipf|mcpf] [--particles N] [--iterations K] [--workers W] [--frames S:I S:I ...]
        [--likelihood robust|ssd] [--free-space F]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from workbench.cli import clutter_floor_arg
from workbench.evaluation import LocalEvaluator, make_evaluator
from workbench.geometry import invert_pose
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator
from workbench.io import bop
from workbench.problem.build import load_bop_problem
from workbench.problem.problem import ProblemConfig
from workbench.render.likelihood import LikelihoodConfig, scene_loglik
from workbench.score.metrics import is_right, position_error, rotation_error


def run_frame(dataset: Path, scene_id: int, im_id: int, config: EstimatorConfig, workers: int,
              problem_config: ProblemConfig = ProblemConfig()) -> dict:
    t0 = time.perf_counter()
    frame, problem = load_bop_problem(dataset, scene_id, im_id, config=problem_config)
    evaluator = make_evaluator(problem, workers)
    try:
        gt = invert_pose(problem.camera.T_cam_world)[None] @ frame.gt_T_cam_obj
        estimator = Estimator(problem, config, evaluator)
        best = estimator.run()
        projected = estimator.estimate  # the search's estimate; ``best`` is it settled
        seconds = time.perf_counter() - t0
    finally:
        evaluator.close()
    local = LocalEvaluator(problem)
    try:
        # The truth is projected with the sink the estimator settled on, as its own hypotheses were.
        truth = local.evaluate(gt[None], np.array([estimator.sink]))
        raw, unsettled = scene_loglik(problem.observed, problem.background,
                                      local.renderer.render(np.stack([gt, projected])), problem.config.likelihood)
        # Per object: the estimate with only that object put at its true pose, projected and scored. A gain means
        # the search missed a better place for that object; a loss, that the likelihood prefers the wrong one.
        swaps = np.repeat(best[None], problem.n_objects + 1, axis=0)
        for k in range(problem.n_objects):
            swaps[k + 1, k] = gt[k]
        swapped = local.evaluate(swaps, np.full(len(swaps), estimator.sink)).loglik
        # How far physics moves the settled scene: how plausible settling left it (compare truth_moved_cm).
        resettled = local.evaluate(best[None], np.array([estimator.sink])).projected[0]
    finally:
        local.close()
    objects = []
    for k, model in enumerate(problem.models):
        pos = 100 * position_error(gt[k], best[k], model.symmetries)
        rot = rotation_error(gt[k], best[k], model.symmetries)
        objects.append({"obj_id": model.obj_id, "position_cm": round(pos, 2), "rotation_deg": round(rot, 1),
                        "right": is_right(gt[k], best[k], model.symmetries),
                        "truth_swap_gain": round(float(swapped[k + 1] - swapped[0]), 1),
                        "truth_moved_cm": round(100 * float(np.linalg.norm(truth.projected[0, k, :3, 3]
                                                                           - gt[k, :3, 3])), 2),
                        # how far settling moved it from the search's (projected) estimate
                        "settled_mm": round(1e3 * float(np.linalg.norm(best[k, :3, 3] - projected[k, :3, 3])), 1),
                        "settled_deg": round(rotation_error(projected[k], best[k]), 1),
                        "settled_moved_cm": round(100 * float(np.linalg.norm(resettled[k, :3, 3]
                                                                             - best[k, :3, 3])), 2),
                        # the estimate's near ties for this object (Estimator.ties), and whether the tied pose is
                        # the right one
                        "ties": [{"turn": t.turn, "gap": round(t.gap, 1),
                                  "right": is_right(gt[k], t.T, model.symmetries)}
                                 for t in estimator.ties if t.obj == k]})
    return {
        "scene_id": scene_id, "im_id": im_id, "objects": objects,
        "all_right": all(o["right"] for o in objects),
        "estimate_loglik": round(estimator.estimate_loglik, 1),
        "settled_loglik_as_given": round(estimator.settled_loglik, 1),
        "estimate_loglik_as_given": round(float(unsettled), 1),
        "truth_loglik_projected": round(float(truth.loglik[0]), 1),
        "truth_loglik_as_annotated": round(float(raw), 1),
        "iterations": estimator.iteration, "evaluations": estimator.evaluations,
        "seconds": round(seconds, 1), "best_kind": estimator.estimate_kind.label,
        "sink_mm": round(1e3 * estimator.sink, 1),
    }


def likelihood_failures(results: list[dict]) -> int:
    """Frames with a wrong object whose estimate scores at least the projected truth: the likelihood's failures
    (the search found something it prefers to the truth)."""
    return sum(not r["all_right"] and r["estimate_loglik"] >= r["truth_loglik_projected"] for r in results)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--proposals", default="default")
    ap.add_argument("--method", default="pipf")
    ap.add_argument("--particles", type=int, default=EstimatorConfig.particles)
    ap.add_argument("--iterations", type=int, default=EstimatorConfig.iterations)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--library-every", type=int, default=EstimatorConfig.library_every,
                    help="iterations between refits of the data-driven candidates")
    ap.add_argument("--frames", nargs="*", help="scene:frame pairs (default: all)")
    ap.add_argument("--likelihood", choices=("robust", "ssd"), default="robust")
    ap.add_argument("--free-space", type=float, default=LikelihoodConfig.free_space,
                    help="robust: a reading behind the predicted surface this many times less likely than one in "
                         "front (LikelihoodConfig.free_space)")
    ap.add_argument("--clutter-floor", type=clutter_floor_arg, default=LikelihoodConfig.clutter_floor,
                    help="robust: what a reading of an unclaimed piece of clutter scores at least; 'none': off")
    ap.add_argument("--out", type=Path, help="JSON lines, one per frame")
    args = ap.parse_args()
    frames = ([tuple(map(int, f.split(":"))) for f in args.frames] if args.frames
              else bop.list_frames(args.dataset))
    config = EstimatorConfig(method=args.method, particles=args.particles, iterations=args.iterations,
                             proposals=args.proposals, seed=args.seed, library_every=args.library_every)
    results = []
    for scene_id, im_id in frames:
        r = run_frame(args.dataset, scene_id, im_id, config, args.workers, ProblemConfig(
            likelihood=LikelihoodConfig(model=args.likelihood, free_space=args.free_space,
                                      clutter_floor=args.clutter_floor)))
        results.append(r)
        line = json.dumps(r)
        print(line, flush=True)
        if args.out:
            with open(args.out, "a") as f:
                f.write(line + "\n")
    right = sum(o["right"] for r in results for o in r["objects"])
    total = sum(len(r["objects"]) for r in results)
    print(f"# {args.proposals} {args.method} N={args.particles} K<={args.iterations}: frames all right "
          f"{sum(r['all_right'] for r in results)}/{len(results)}, objects right {right}/{total}, "
          f"median position error {np.median([o['position_cm'] for r in results for o in r['objects']]):.1f} cm, "
          f"estimate >= projected truth in {sum(r['estimate_loglik'] >= r['truth_loglik_projected'] for r in results)}"
          f"/{len(results)} (of them wrong: {likelihood_failures(results)}), "
          f"truth above the estimate in {sum(r['truth_loglik_projected'] > r['estimate_loglik'] for r in results)}"
          f"/{len(results)}, median {np.median([r['seconds'] for r in results]):.0f} s per frame", file=sys.stderr)
    objects = [o for r in results for o in r["objects"]]
    tied = [o for o in objects if o["ties"]]
    print(f"# near ties: {len(tied)} objects have one ({sum(not o['right'] for o in tied)} of them wrong, "
          f"{sum(any(t['right'] for t in o['ties']) for o in tied)} with the right pose among the ties); "
          f"{sum(not o['right'] and not o['ties'] for o in objects)} wrong objects have none", file=sys.stderr)


if __name__ == "__main__":
    main()
