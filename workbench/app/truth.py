"""The estimate against the dataset's ground truth (scene_gt.json), scored exactly as ``workbench score`` scores a
results CSV (``bench.scoring``): instances of one object matched nearest first, errors up to the model's
symmetries in the camera frame, ADD-S on the same model points, right within ``metrics.RIGHT_CM`` and
``RIGHT_DEG``. The engine sends the rows every iteration (``protocol.TruthErrors``); the panel shows them."""

from __future__ import annotations

import numpy as np

from workbench.app.markdown import escape
from workbench.metrics import RIGHT_CM, RIGHT_DEG, add_s, is_right, position_error, rotation_error


def truth_rows(frame, problem, estimate: np.ndarray, points: list) -> list[dict]:
    """Per ground-truth object of ``frame`` (in its order) a row {"index", "obj_id", "position_cm",
    "rotation_deg", "add_s_mm", "right"}; ``estimate`` (K, 4, 4) table frame, one pose per object of ``problem``;
    ``points``: per object the ADD-S points (``engine_labels.truth_points``)."""
    from workbench.bench.scoring import match

    T_cam_world = problem.camera.T_cam_world
    est_cam = T_cam_world[None] @ np.asarray(estimate, dtype=np.float64)
    obj_ids = [m.obj_id for m in problem.models]
    rows: dict[int, dict] = {}
    for obj_id in dict.fromkeys(frame.object_ids):
        gi = [k for k, o in enumerate(frame.object_ids) if o == obj_id]
        ei = [k for k, o in enumerate(obj_ids) if o == obj_id]
        model = problem.models[ei[0]] if ei else None
        sym = None if model is None else model.symmetries
        pairs = dict(match(frame.gt_T_cam_obj[gi], est_cam[ei].reshape(-1, 4, 4), sym)) if ei else {}
        for i, k in enumerate(gi):
            row = {"index": k, "obj_id": int(obj_id), "position_cm": float("nan"), "rotation_deg": float("nan"),
                   "add_s_mm": float("nan"), "right": False}
            if i in pairs:
                T_gt, T_est = frame.gt_T_cam_obj[k], est_cam[ei[pairs[i]]]
                row.update(position_cm=100 * position_error(T_gt, T_est, sym),
                           rotation_deg=rotation_error(T_gt, T_est, sym),
                           add_s_mm=1000 * add_s(T_gt, T_est, points[ei[pairs[i]]]),
                           right=bool(is_right(T_gt, T_est, sym)))
            rows[k] = row
    return [rows[k] for k in sorted(rows)]


def truth_markdown(iteration: int, rows: list[dict], names: list[str]) -> str:
    """The table the panel shows: one row per object (``names``: the objects' display names, by index)."""
    if not rows:
        return ""
    lines = []
    for r in rows:
        name = escape(names[r["index"]] if r["index"] < len(names) else f"obj_{r['obj_id']:06d}")
        if not np.isfinite(r["position_cm"]):
            lines.append(f"| {name} | — | — | — | no estimate |")
            continue
        verdict = "right" if r["right"] else "**wrong**"
        lines.append(f"| {name} | {r['position_cm']:.2f} | {r['rotation_deg']:.1f} | {r['add_s_mm']:.1f} | {verdict} |")
    n_right = sum(r["right"] for r in rows)
    return (f"**Estimate vs ground truth** · iteration {iteration} · {n_right}/{len(rows)} right\n\n"
            "| object | position (cm) | rotation (°) | ADD-S (mm) | |\n|---|---:|---:|---:|---|\n" + "\n".join(lines)
            + f"\n\n<small>as `workbench score`: up to the model's symmetries; right within {RIGHT_CM:g} cm and "
            f"{RIGHT_DEG:g}°</small>")
