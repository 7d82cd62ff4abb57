"""A tracked sequence's numbers from its results CSV (``workbench track``): seconds per frame (the CSV's ``time``),
objects right per frame (``workbench score``'s rule), and consistency: for objects that do not move, how much each
estimate changes from frame to frame in the world frame of ``scene_camera_world.json`` (position mm, rotation
degrees, up to the model's symmetries), against how much the annotations change.

    PYTHONPATH=. python benchmarks/track_sequence.py ../shared/datasets/ycbv-real-seq results.csv --scene 1
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from workbench.geometry import invert_pose
from workbench.io import bop
from workbench.io.results import ResultRow, read_results_csv
from workbench.score.metrics import position_error, rotation_error
from workbench.score.scoring import score_results
from workbench.track.motion import read_world_poses


def top_poses(rows: list[ResultRow], scene_id: int) -> dict[int, dict[int, np.ndarray]]:
    """Per image id, per obj_id, the most likely row's pose (camera frame); one instance per object."""
    out: dict[int, dict[int, tuple[float, np.ndarray]]] = {}
    for r in rows:
        if r.scene_id == scene_id:
            best = out.setdefault(r.im_id, {}).get(r.obj_id)
            if best is None or r.score > best[0]:
                out[r.im_id][r.obj_id] = (r.score, r.T_cam_obj)
    return {i: {o: T for o, (_, T) in objs.items()} for i, objs in out.items()}


def changes(poses: dict[int, dict[int, np.ndarray]], world: dict[int, np.ndarray], symmetries: dict[int, np.ndarray]
            ) -> tuple[np.ndarray, np.ndarray]:
    """Frame-to-frame change of each object's pose in the world frame, consecutive image ids only -> (mm (M,),
    degrees (M,)), up to each model's symmetries."""
    mm, deg = [], []
    for i in sorted(poses):
        if i + 1 not in poses:
            continue
        for obj, T in poses[i].items():
            if obj in poses[i + 1]:
                A = invert_pose(world[i]) @ T
                B = invert_pose(world[i + 1]) @ poses[i + 1][obj]
                mm.append(1000 * position_error(A, B, symmetries[obj]))
                deg.append(rotation_error(A, B, symmetries[obj]))
    return np.array(mm), np.array(deg)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset", type=Path)
    p.add_argument("results", type=Path)
    p.add_argument("--scene", type=int, required=True)
    args = p.parse_args()
    rows = [r for r in read_results_csv(args.results) if r.scene_id == args.scene]
    frames = score_results(args.dataset, rows)
    seconds = {r.im_id: r.time for r in rows}
    for f in frames:
        print(f"frame {f.im_id:3d}: {seconds[f.im_id]:6.1f} s, {sum(o.right for o in f.objects)}/{len(f.objects)} "
              "right")
    tracked = [seconds[i] for i in sorted(seconds)[1:]]
    print(f"# first frame {seconds[min(seconds)]:.1f} s; tracked frames: median {np.median(tracked):.2f} s, "
          f"max {np.max(tracked):.2f} s; whole sequence {sum(seconds.values()):.1f} s")
    right = [sum(o.right for o in f.objects) for f in frames]
    print(f"# objects right: {sum(right)}/{sum(len(f.objects) for f in frames)}; frames with every object right: "
          f"{sum(f.right for f in frames)}/{len(frames)}")
    world = read_world_poses(bop.scene_folder(args.dataset, args.scene))
    poses = top_poses(rows, args.scene)
    models = bop.load_models(args.dataset, sorted({o for objs in poses.values() for o in objs}))
    symmetries = {o: m.symmetries for o, m in models.items()}
    mm, deg = changes(poses, world, symmetries)
    truth = {i: {o: T for o, T in zip(bop.load_frame(args.dataset, args.scene, i).object_ids,
                                      bop.load_frame(args.dataset, args.scene, i).gt_T_cam_obj)} for i in poses}
    gmm, gdeg = changes(truth, world, symmetries)
    print(f"# frame-to-frame change in the world frame: median {np.median(mm):.2f} mm, {np.median(deg):.2f} deg; "
          f"p90 {np.percentile(mm, 90):.2f} mm, {np.percentile(deg, 90):.2f} deg (annotations: median "
          f"{np.median(gmm):.2f} mm, {np.median(gdeg):.2f} deg)")


if __name__ == "__main__":
    main()
