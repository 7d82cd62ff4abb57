"""How often the search's first candidate library holds a right pose: per frame and object, whether any candidate
fitted to the clusters of all observed points (``datadriven.build_library``, as ``DefaultSearch.start`` fits them)
is within 2 cm and 10 degrees of the truth, up to the model's symmetries. The search can only put together what its
candidates hold, so this is the first thing to look at when the truth scores above the estimate. Seconds, not a
whole run, per frame.

    .venv/bin/python benchmarks/library_coverage.py DATASET [S:I ...]   (default: every frame)

Prints one line per frame (a 1 or 0 per object, in scene_gt order) and the total.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from workbench.geometry import invert_pose
from workbench.inference.search import datadriven
from workbench.inference.search.geometry import SearchGeometry
from workbench.inference.search.scenepoints import clusters
from workbench.io import bop
from workbench.problem.build import load_bop_problem
from workbench.score.metrics import is_right


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("frames", nargs="*", help="scene:frame pairs (default: all)")
    args = ap.parse_args()
    frames = [tuple(map(int, f.split(":"))) for f in args.frames] or bop.list_frames(args.dataset)
    objects = right = 0
    seconds = 0.0
    for scene_id, im_id in frames:
        frame, problem = load_bop_problem(args.dataset, scene_id, im_id)
        gt = invert_pose(problem.camera.T_cam_world)[None] @ frame.gt_T_cam_obj
        g = SearchGeometry.of(problem, upright=False)
        t0 = time.perf_counter()
        library = datadriven.build_library(problem, clusters(g.points.points), g)
        seconds += time.perf_counter() - t0
        row = [any(is_right(gt[k], T, m.symmetries) for T in library.poses[k]) for k, m in enumerate(problem.models)]
        objects, right = objects + len(row), right + sum(row)
        print(f"{scene_id}:{im_id} {''.join(str(int(r)) for r in row)}", flush=True)
    print(f"{right}/{objects} objects with a right candidate; library built in {seconds:.1f} s in all")


if __name__ == "__main__":
    main()
