"""How far physics projection moves the *true* scenes of a BOP dataset: a true scene is at rest, so projection
should leave it where it is. Prints, per object and frame, how far projection moved it (mean model-point
displacement; the same without the vertical shift of its centre; the vertical and sideways shifts of the centre;
rotation) and a summary per object (median, p90, max). The vertical shift is reported apart because where the
fitted table plane lies above the true objects' bottoms (by 4-11 mm on ycbv-real-dev: the annotated objects
sink into the plane fitted to the table's depth), projection lifts them onto it: that is the table estimate
disagreeing with the annotation, not physics moving a resting scene.

    PYTHONPATH=. python benchmarks/true_scene_drift.py ../shared/datasets/ycbv-real-dev
    PYTHONPATH=. python benchmarks/true_scene_drift.py DATASET --reference   # also: simplified vs full shapes

``--reference`` also projects each true scene with the unsimplified collision shapes (every object as the convex
hull of all its vertices, concave ones as fine V-HACD pieces) and reports how far the default shapes' resting
poses are from those: the cost in accuracy of the simplified geometry.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from workbench.geometry import invert_pose, rotation_angle
from workbench.io import bop, readers
from workbench.physics import STATUS_NAMES, PhysicsConfig, PhysicsProjector
from workbench.physics.collision import collision_shape_for
from workbench.problem.build import load_bop_problem
from workbench.score.metrics import model_points


def movement(T_a: np.ndarray, T_b: np.ndarray, points: list[np.ndarray]) -> np.ndarray:
    """How far each object (K,) moved from scene T_a to scene T_b (K, 4, 4) -> (K, 5): mean model-point
    displacement, the same without the vertical shift of the centre, vertical and horizontal shift of the
    centre (all m) and rotation (rad)."""
    out = []
    for Ta, Tb, p in zip(T_a, T_b, points):
        pa = p @ Ta[:3, :3].T + Ta[:3, 3]
        pb = p @ Tb[:3, :3].T + Tb[:3, 3]
        shift = pb.mean(0) - pa.mean(0)
        flat = pb - [0.0, 0.0, shift[2]]
        out.append([np.mean(np.linalg.norm(pb - pa, axis=1)), np.mean(np.linalg.norm(flat - pa, axis=1)),
                    shift[2], np.linalg.norm(shift[:2]), float(rotation_angle(Ta[:3, :3].T @ Tb[:3, :3]))])
    return np.array(out)


def summary(rows: list[tuple[str, np.ndarray]], title: str, column: int = 0) -> None:
    print(f"\n{title}, mm")
    print("| object | frames | median | p90 | max |")
    print("|---|---|---|---|---|")
    names = sorted({n for n, _ in rows})
    for name in names + ["all"]:
        v = np.array([m[column] for n, m in rows if name in (n, "all")]) * 1e3
        print(f"| {name} | {len(v)} | {np.median(v):.1f} | {np.percentile(v, 90):.1f} | {v.max():.1f} |")


def object_names(dataset: Path) -> dict[int, str]:
    """obj_id -> the "name" of models_info.json where it has one (YCB-Video's do), else "obj N"."""
    info = readers.read_json(bop._models_dir(dataset) / "models_info.json")
    return {int(k): v.get("name", f"obj {k}") for k, v in info.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--reference", action="store_true", help="compare with unsimplified collision shapes")
    parser.add_argument("--rolling-friction", type=float, default=None,
                        help="override PhysicsConfig's rolling and spinning friction (m)")
    parser.add_argument("--solver-residual", type=float, default=None, help="override PhysicsConfig's")
    parser.add_argument("--pyramid-friction", action="store_true", help="Bullet's pyramid friction, not its cone")
    parser.add_argument("--awake", action="store_true", help="calm bodies stay awake (PhysicsConfig.sleep_calm off)")
    args = parser.parse_args()
    physics = PhysicsConfig(cone_friction=not args.pyramid_friction, sleep_calm=not args.awake)
    if args.rolling_friction is not None:
        physics = dataclasses.replace(physics, rolling_friction=args.rolling_friction,
                                      spinning_friction=args.rolling_friction)
    if args.solver_residual is not None:
        physics = dataclasses.replace(physics, solver_residual=args.solver_residual)
    names = object_names(args.dataset)
    drift, versus = [], []
    print("| scene | frame | object | shape | status | steps | moved mm | without lift mm | up mm | sideways mm "
          "| rotation deg | ms |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for scene_id, im_id in bop.list_frames(args.dataset):
        frame, problem = load_bop_problem(args.dataset, scene_id, im_id)
        models = problem.models
        T_world_obj = invert_pose(problem.camera.T_cam_world)[None] @ frame.gt_T_cam_obj
        points = [model_points(m.mesh, 500) for m in models]
        with PhysicsProjector(models, problem.table, physics) as projector:
            t0 = time.perf_counter()
            rest, status, steps = projector.project(T_world_obj)
            ms = 1e3 * (time.perf_counter() - t0)
            shapes = projector.shapes
        moved = movement(T_world_obj, rest, points)
        for m, s, mv in zip(models, shapes, moved):
            name = names.get(m.obj_id, f"obj {m.obj_id}")
            drift.append((name, mv))
            print(f"| {scene_id} | {im_id} | {name} | {s.describe()} | {STATUS_NAMES[status]} | {steps} "
                  f"| {mv[0] * 1e3:.1f} | {mv[1] * 1e3:.1f} | {mv[2] * 1e3:.1f} | {mv[3] * 1e3:.1f} "
                  f"| {np.degrees(mv[4]):.1f} | {ms:.1f} |")
        if args.reference:
            full = [collision_shape_for(m.mesh, kind="reference") for m in models]
            with PhysicsProjector(models, problem.table, physics, shapes=full) as projector:
                ref, _, _ = projector.project(T_world_obj)
            for m, mv in zip(models, movement(ref, rest, points)):
                versus.append((names.get(m.obj_id, f"obj {m.obj_id}"), mv))
    summary(drift, "True scenes moved by projection: mean model-point movement per object")
    summary(drift, "The same without the vertical shift (where the truth sinks into the fitted table plane)", 1)
    if versus:
        summary(versus, "Resting poses, simplified shapes against unsimplified ones: mean model-point distance")


if __name__ == "__main__":
    main()
