"""How well the depth pins down each object's rotation about its own axis of (near) rotational symmetry.

For every annotated object of a BOP dataset whose mesh is nearly a body of revolution (a can, a bottle, a marker:
two equal principal moments of inertia), the true scene is scored by our likelihood with that one object turned
about its axis by 90 and 180 degrees, before physics (as annotated) and after it (projected). A difference of a
few log-units, against the thousands that separate a wrong scene, means that no depth-only estimator can tell the
turned pose from the true one; such an object is then "right" only by chance under a rotation metric that does
not know its symmetry.

    .venv/bin/python benchmarks/axis_ambiguity.py ../shared/datasets/ycbv-real-dev [--frames S:I ...]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from workbench.evaluation import LocalEvaluator
from workbench.geometry import invert_pose, make_pose
from workbench.io import bop
from workbench.problem.build import load_bop_problem


def symmetry_axis(mesh, tolerance: float = 0.08) -> np.ndarray | None:
    """Unit axis (3,) in the object frame, through the centre of mass, of a mesh whose principal moments of
    inertia have two nearly equal values (relative difference below ``tolerance``); None otherwise."""
    values, vectors = np.linalg.eigh(mesh.convex_hull.moment_inertia)
    for odd, (a, b) in ((0, (1, 2)), (2, (0, 1))):
        if abs(values[a] - values[b]) < tolerance * max(values[a], values[b]):
            return vectors[:, odd]
    return None


def turned(T: np.ndarray, axis: np.ndarray, centre: np.ndarray, angle: float) -> np.ndarray:
    """Pose T (4, 4) turned by ``angle`` (rad) about the object-frame ``axis`` (3,) through ``centre`` (3,)."""
    a = axis / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    return T @ make_pose(R, centre - R @ centre)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--frames", nargs="*", help="scene:frame pairs (default: all)")
    args = ap.parse_args()
    frames = ([tuple(map(int, f.split(":"))) for f in args.frames] if args.frames
              else bop.list_frames(args.dataset))
    print("frame  object  turn  loglik change as annotated  loglik change projected")
    for scene_id, im_id in frames:
        frame, problem = load_bop_problem(args.dataset, scene_id, im_id)
        gt = invert_pose(problem.camera.T_cam_world)[None] @ frame.gt_T_cam_obj
        evaluator = LocalEvaluator(problem)
        try:
            scenes, labels = [gt], []
            for k, model in enumerate(problem.models):
                axis = symmetry_axis(model.mesh)
                if axis is None:
                    continue
                for deg in (90, 180):
                    s = gt.copy()
                    s[k] = turned(gt[k], axis, model.mesh.convex_hull.center_mass, np.radians(deg))
                    scenes.append(s)
                    labels.append((model.obj_id, deg))
            raw = evaluator.renderer.render(np.stack(scenes))
            from workbench.render.likelihood import scene_loglik

            annotated = scene_loglik(problem.observed, problem.background, raw, problem.config.likelihood)
            projected = evaluator.evaluate(np.stack(scenes)).loglik
        finally:
            evaluator.close()
        for i, (obj_id, deg) in enumerate(labels, start=1):
            print(f"{scene_id}:{im_id:<4} {obj_id:>6} {deg:>5}  {annotated[i] - annotated[0]:+26.1f}  "
                  f"{projected[i] - projected[0]:+23.1f}", flush=True)


if __name__ == "__main__":
    main()
