"""``workbench label`` against a sequence's own ground truth: per frame, the median position and rotation error of
the labels (symmetry-aware, as the benchmarks count them), against the frames' own tracked answers and the first
frame's answer carried alone; which frames are flagged; the seconds of each stage. Nothing is written into the
dataset.

    python benchmarks/label_sequence.py ../shared/datasets/ycbv-real-seq --scene 1 2 [--frames 1:20] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from workbench.inference.config import EstimatorConfig
from workbench.io import bop
from workbench.label.config import LabelConfig
from workbench.label.run import label_sequence
from workbench.score.metrics import position_error, rotation_error
from workbench.track.config import TrackConfig
from workbench.track.frames import sequence_frames


def errors(gt: np.ndarray, poses: list[np.ndarray | None], models: list) -> np.ndarray:
    """Per object (position mm, rotation deg) of camera-frame ``poses`` against ``gt`` (K, 4, 4) -> (K, 2), NaN
    where there is no pose."""
    out = np.full((len(gt), 2), np.nan)
    for k, (G, T) in enumerate(zip(gt, poses)):
        if T is not None:
            out[k] = 1000 * position_error(G, T, models[k].symmetries), rotation_error(G, T, models[k].symmetries)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset", type=Path)
    p.add_argument("--scene", type=int, nargs="+", default=[1, 2])
    p.add_argument("--frames", default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fit-frames", type=int, default=LabelConfig().fit_frames)
    p.add_argument("--snap", action="store_true")
    args = p.parse_args()
    for scene in args.scene:
        frames = sequence_frames(args.dataset, scene, None, args.frames)
        run = label_sequence(args.dataset, scene, frames, EstimatorConfig(seed=args.seed), TrackConfig(),
                             LabelConfig(fit_frames=args.fit_frames, snap=args.snap))
        first = min(run.tracked)
        ids = run.labels.obj_ids
        models = [m for m in (bop.load_models(args.dataset, ids)[i] for i in ids)]
        rows = {"labels": [], "tracked": [], "first carried": []}
        for im_id in run.labels.frames:
            gt = bop.load_frame(args.dataset, scene, im_id, None, ids).gt_T_cam_obj
            T_cw = run.labels.T_cam_world[im_id]
            rows["labels"].append(errors(gt, run.labels.camera_poses(im_id), models))
            rows["tracked"].append(errors(gt, [T_cw @ T for T in run.tracked[im_id]], models))
            rows["first carried"].append(errors(gt, [T_cw @ T for T in run.tracked[first]], models))
        print(f"scene {scene}: {len(frames)} frames, objects {ids}; seconds " +
              ", ".join(f"{k} {v:.1f}" for k, v in run.seconds.items()) + f"; flagged {run.flagged or 'none'}")
        for name, e in rows.items():
            e = np.array(e)  # (F, K, 2)
            per_frame = np.nanmedian(e, axis=1)  # (F, 2): each frame's median over objects
            print(f"  {name:>13}: per-frame median error, worst frame {per_frame[:, 0].max():.1f} mm / "
                  f"{per_frame[:, 1].max():.1f} deg; per object (mean over frames) mm "
                  + " ".join(f"{v:.1f}" for v in np.nanmean(e[..., 0], axis=0)) + "; deg "
                  + " ".join(f"{v:.1f}" for v in np.nanmean(e[..., 1], axis=0)))
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
