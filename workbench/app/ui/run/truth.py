"""The estimate against the dataset's ground truth (scene_gt.json), scored exactly as ``workbench score`` scores a
results CSV (``score.scoring``): instances of one object matched nearest first, errors up to the model's
symmetries in the camera frame, ADD-S on the same model points, right within ``score.metrics.RIGHT_CM`` and
``RIGHT_DEG``; beside them the confidence the posterior gives the matched estimate (its top mode's probability),
once the run was settled. The engine sends the rows every iteration (``protocol.TruthErrors``); the panel shows
them."""

from __future__ import annotations

import numpy as np

from workbench.app.ui.run.modes import chance
from workbench.app.ui.widgets.colors import named
from workbench.score.metrics import RIGHT_CM, RIGHT_DEG, add_s, is_right, position_error, rotation_error


def truth_rows(frame, problem, estimate: np.ndarray, points: list, posterior=None) -> list[dict]:
    """Per ground-truth object of ``frame`` (in its order) a row {"index", "obj_id", "position_cm",
    "rotation_deg", "add_s_mm", "right", "confidence"}; ``estimate`` (K, 4, 4) table frame, one pose per object of
    ``problem``; ``points``: per object the ADD-S points (``engine_labels.truth_points``); ``posterior``
    (``inference.answer.posterior.Posterior`` of ``estimate``, or None): "confidence" is the matched object's top mode's
    probability, NaN without a posterior."""
    from workbench.score.scoring import match

    T_cam_world = problem.camera.T_cam_world
    est_cam = T_cam_world[None] @ np.asarray(estimate, dtype=np.float64)
    obj_ids = [m.obj_id for m in problem.models]
    confidence = top_probabilities(posterior, len(obj_ids))
    rows: dict[int, dict] = {}
    for obj_id in dict.fromkeys(frame.object_ids):
        gi = [k for k, o in enumerate(frame.object_ids) if o == obj_id]
        ei = [k for k, o in enumerate(obj_ids) if o == obj_id]
        model = problem.models[ei[0]] if ei else None
        sym = None if model is None else model.symmetries
        pairs = dict(match(frame.gt_T_cam_obj[gi], est_cam[ei].reshape(-1, 4, 4), sym)) if ei else {}
        for i, k in enumerate(gi):
            row = {"index": k, "obj_id": int(obj_id), "position_cm": float("nan"), "rotation_deg": float("nan"),
                   "add_s_mm": float("nan"), "right": False, "confidence": float("nan")}
            if i in pairs:
                T_gt, T_est = frame.gt_T_cam_obj[k], est_cam[ei[pairs[i]]]
                row.update(position_cm=100 * position_error(T_gt, T_est, sym),
                           rotation_deg=rotation_error(T_gt, T_est, sym),
                           add_s_mm=1000 * add_s(T_gt, T_est, points[ei[pairs[i]]]),
                           right=bool(is_right(T_gt, T_est, sym)), confidence=confidence[ei[pairs[i]]])
            rows[k] = row
    return [rows[k] for k in sorted(rows)]


def top_probabilities(posterior, n_objects: int) -> list[float]:
    """(K,) each object's top mode's probability under ``posterior`` (None: all NaN), as the panel shows it: of
    all the object's chances, elsewhere included (``modes.chance``)."""
    out = [float("nan")] * n_objects
    for o in posterior.objects if posterior is not None else []:
        if 0 <= o.obj < n_objects:
            out[o.obj] = float(chance(o, o.modes[0]))
    return out


def confidence_cell(value: float) -> str:
    """The table's confidence: "0.84", or "–" while the run has no posterior (not finished or settled)."""
    return f"{value:.2f}" if np.isfinite(value) else "–"


def truth_markdown(iteration: int, rows: list[dict], names: list[str]) -> str:
    """The table the panel shows: one row per object (``names``: the objects' display names, by index)."""
    if not rows:
        return ""
    lines = []
    for r in rows:
        name = named(r["index"], names[r["index"]] if r["index"] < len(names) else f"obj_{r['obj_id']:06d}")
        if not np.isfinite(r["position_cm"]):
            lines.append(f"| {name} | — | — | — | no estimate | – |")
            continue
        verdict = "right" if r["right"] else "**wrong**"
        lines.append(f"| {name} | {r['position_cm']:.2f} | {r['rotation_deg']:.1f} | {r['add_s_mm']:.1f} | {verdict} "
                     f"| {confidence_cell(r.get('confidence', float('nan')))} |")
    n_right = sum(r["right"] for r in rows)
    return (f"**Estimate vs ground truth** · iteration {iteration} · {n_right}/{len(rows)} right\n\n"
            "| object | pos. (cm) | rot. (°) | ADD-S (mm) | | p |\n|---|---:|---:|---:|:---:|---:|\n" + "\n".join(lines)
            + f"\n\n<small>as `workbench score`; right: within {RIGHT_CM:g} cm, {RIGHT_DEG:g}°; p: confidence (– until "
              "the run ends)</small>")
