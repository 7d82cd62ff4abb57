"""A BOP results CSV scored against a dataset's ground truth (``workbench score``).

Each ground-truth instance of a frame is matched to one estimate row of the same object (greedily, nearest
first, when a frame holds several instances), and scored up to the model's symmetries (models_info.json):
position error (cm), rotation error (deg), ADD-S (mm). An object is *right* within ``RIGHT_CM`` and
``RIGHT_DEG``, the tolerances of docs/benchmarks.md; a frame is right when all its objects are. Poses stay in the
camera frame (OpenCV, metres): both errors are the same in any frame both poses share.

With ``vsd`` (``score_results``), each object is also scored as BOP 2019 scores it: by what the camera sees of it,
the Visible Surface Discrepancy (``vsd.py``) against the frame's depth image, and by the MSSD and MSPD of its
vertices up to the model's symmetries (``ar.py``), the same estimate matched to the same instance; AR is the mean of
AR_VSD, AR_MSSD and AR_MSPD, as the BOP leaderboard reports it.

Where the dataset says how much of each object the camera sees (scene_gt_info.json), objects under
``gt_info.HIDDEN_VISIB`` are also counted apart: BOP's test targets leave them out, the depth hardly constrains
them. Sets `workbench make-scenes` wrote are also counted per category (scenes.json).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.io import bop
from workbench.io.results import ResultRow
from workbench.score import ar, calibration
from workbench.score.calibration import ObjectModes
from workbench.score.gt_info import HIDDEN_VISIB, gt_info_path, scene_categories, scenes_path, visib_fractions
from workbench.score.metrics import (
    RIGHT_CM,
    RIGHT_DEG,
    add_s,
    is_right,
    model_points,
    mssd,
    position_error,
    rotation_error,
)
from workbench.score.vsd import VSDConfig, diameter, frame_vsd

# Modes' probabilities as `estimate` writes them (rounded to 12 digits each) sum to 1 within this.
MODE_SUM_TOLERANCE = 1e-3


@dataclass(frozen=True)
class ObjectScore:
    """One ground-truth instance against its estimate; errors NaN and ``right`` False when it has none."""

    scene_id: int
    im_id: int
    obj_id: int
    position_cm: float
    rotation_deg: float
    add_s_mm: float
    right: bool
    # BOP's VSD (``vsd.ObjectVSD``; 1, False, 0 without an estimate); NaN, None and NaN when not scored by VSD
    vsd: float = np.nan
    vsd_right: bool | None = None
    ar_vsd: float = np.nan
    # BOP's MSSD (mm) and MSPD (px) up to the symmetries and the object's shares of AR_MSSD's and AR_MSPD's
    # thresholds (``ar``; NaN errors and 0 shares without an estimate); NaN when not scored as BOP scores
    mssd_mm: float = np.nan
    mspd_px: float = np.nan
    ar_mssd: float = np.nan
    ar_mspd: float = np.nan
    visib_fract: float = np.nan  # scene_gt_info.json's; NaN where the dataset does not say

    @property
    def estimated(self) -> bool:
        return bool(np.isfinite(self.position_cm))

    @property
    def hidden(self) -> bool:
        """Under ``HIDDEN_VISIB`` of it visible (False where the dataset does not say)."""
        return bool(self.visib_fract < HIDDEN_VISIB)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class FrameScore:
    scene_id: int
    im_id: int
    objects: list[ObjectScore]
    unmatched_rows: int  # estimate rows of objects the ground truth does not hold (or holds fewer of)
    # Per object instance with an estimate: its rows as the modes of its posterior (``calibration``)
    modes: list[ObjectModes] = field(default_factory=list)
    category: str | None = None  # scenes.json's, in sets `workbench make-scenes` wrote

    @property
    def right(self) -> bool:
        return all(o.right for o in self.objects)


def _load_shapes(dataset: Path, obj_ids: list[int]) -> dict:
    """The models, for their shapes and symmetries only: the loader's warning that an open mesh's mass comes from
    its convex hull concerns physics, not scoring, so it is not shown here (a mesh wound inside out is)."""
    level = bop.hull_log.level
    bop.hull_log.setLevel(logging.ERROR)
    try:
        return bop.load_models(dataset, obj_ids)
    finally:
        bop.hull_log.setLevel(level)


def match(gt: np.ndarray, est: np.ndarray, symmetries: np.ndarray) -> list[tuple[int, int]]:
    """Instances of one object: pairs (ground-truth index, estimate index), nearest first, each used once.
    ``gt`` (G, 4, 4), ``est`` (E, 4, 4), one frame; ground truth rows that are NaN are never matched."""
    pairs = sorted((position_error(g, e, symmetries), i, j)
                   for i, g in enumerate(gt) if np.isfinite(g).all() for j, e in enumerate(est))
    used_gt, used_est, out = set(), set(), []
    for _, i, j in pairs:
        if i not in used_gt and j not in used_est:
            used_gt.add(i)
            used_est.add(j)
            out.append((i, j))
    return out


def instance_groups(rows: list[ResultRow], n: int) -> list[list[ResultRow]]:
    """One model's rows of one frame (file order) as up to ``n`` instances, each its rows best first: runs of rows
    whose scores sum to 1, as `estimate` writes each instance's modes (its posterior). Rows that do not fall into
    such runs (another tool's results: one row per instance, any score) are each an instance of their own, the
    ``n`` best by score kept (the others are taken for modes; all of them the one instance's when ``n`` is 1)."""
    groups, run, total = [], [], 0.0
    for r in rows:
        run.append(r)
        total += r.score
        if abs(total - 1.0) < MODE_SUM_TOLERANCE:
            groups.append(sorted(run, key=lambda r: -r.score))
            run, total = [], 0.0
    if run or len(groups) > n:
        ranked = sorted(rows, key=lambda r: -r.score)
        return [ranked] if n == 1 and ranked else [[r] for r in ranked[:n]]
    return groups


def check_modes(rows: list[ResultRow], n: int, path: Path | None) -> None:
    """InputError naming the file, the frame and the object when one object's rows, more than its ``n`` instances
    and so read as the modes of its posterior (``instance_groups``), hold scores that are no probabilities: each in
    [0, 1], all together at most 1 per instance. Calibration computed on them would mean nothing."""
    if len(rows) <= n:
        return
    scores = np.array([r.score for r in rows])
    total = float(scores.sum())
    if scores.min() < 0.0 or scores.max() > 1.0 or total > n * (1.0 + MODE_SUM_TOLERANCE):
        r = rows[0]
        raise InputError(path, f"scene {r.scene_id} image {r.im_id} object {r.obj_id}: {len(rows)} rows for "
                               f"{n} instance(s) are read as the modes of its posterior, whose scores are "
                               f"probabilities, but they range from {scores.min():.3g} to {scores.max():.3g} and sum "
                               f"to {total:.3g}; give each instance one row, or modes whose probabilities sum to 1")


def score_results(dataset: Path, rows: list[ResultRow], split: str | None = None,
                  results_path: Path | None = None, vsd: VSDConfig | None = None) -> list[FrameScore]:
    """Every frame that ``rows`` (a results CSV, ``io.results.read_results_csv``) holds, scored against the dataset's
    scene_gt.json, frames in (scene, image) order. InputError, naming the file, when a frame is not in the dataset
    or has no ground truth. With ``vsd``, each object's VSD too (renders each object alone at the estimated and the
    true pose, at the frame's resolution: OpenGL in this process)."""
    frames: dict[tuple[int, int], list[ResultRow]] = {}
    for r in rows:
        frames.setdefault((r.scene_id, r.im_id), []).append(r)
    known = set(bop.list_frames(dataset, split=split))
    categories = scene_categories(dataset) if scenes_path(dataset).is_file() else {}
    missing = sorted(set(frames) - known)
    if missing:
        raise InputError(results_path, f"{len(missing)} frame(s) are not in {dataset}, e.g. scene {missing[0][0]} "
                         f"image {missing[0][1]}: is this the dataset the results were made on?")
    # obj_id -> (symmetries, ADD-S points, mesh, diameter m, BOP's symmetries (continuous ones sampled finer))
    models: dict[int, tuple] = {}
    out = []
    for (scene_id, im_id), mine in sorted(frames.items()):
        try:
            frame = bop.load_frame(dataset, scene_id, im_id, split)
        except InputError as err:
            if "no scene_gt.json" in err.problem:  # the estimate's question (which objects?) is not score's
                raise InputError(err.path, f"image {im_id} has no scene_gt.json: nothing to score against") from None
            raise
        if frame.gt_T_cam_obj is None:
            raise InputError(dataset, f"scene {scene_id} image {im_id} has no scene_gt.json: nothing to score against")
        new = sorted(set(frame.object_ids) - set(models))
        fine = bop.load_symmetries(dataset, new, ar.continuous_steps()) if vsd is not None and new else {}
        for obj_id, m in _load_shapes(dataset, new).items():
            models[obj_id] = (m.symmetries, model_points(m.mesh, 500), m.mesh,
                              diameter(m.mesh) if vsd is not None else np.nan, fine.get(obj_id))
        objects, matched, extra, modes = [], 0, 0, []
        seen = []  # per ground-truth instance, in the order of ``objects``: (obj_id, T_gt, T_est or None)
        visib = visib_fractions(frame) if gt_info_path(frame).is_file() else [np.nan] * len(frame.object_ids)
        for obj_id in dict.fromkeys(frame.object_ids):
            gi = [k for k, o in enumerate(frame.object_ids) if o == obj_id]
            # One estimate per instance, its top row: further rows are other modes of the posterior (the same
            # instance's less likely poses), which must not be matched to the truth in the estimate's place.
            rows = [r for r in mine if r.obj_id == obj_id]
            check_modes(rows, len(gi), results_path)
            groups = instance_groups(rows, len(gi))
            est = [g[0].T_cam_obj for g in groups]
            extra += len(rows) - len(groups)
            sym, points = models[obj_id][:2]
            pairs = dict(match(frame.gt_T_cam_obj[gi], np.array(est).reshape(-1, 4, 4), sym))
            matched += len(pairs)
            for i, j in pairs.items():  # each instance's modes, against the truth its estimate was matched to
                modes.append(calibration.object_modes(frame.gt_T_cam_obj[gi[i]],
                                                      [(r.score, r.T_cam_obj) for r in groups[j]], sym))
            for i, k in enumerate(gi):
                T_gt = frame.gt_T_cam_obj[k]
                if i not in pairs:
                    objects.append(ObjectScore(scene_id, im_id, obj_id, np.nan, np.nan, np.nan, False,
                                               visib_fract=visib[k]))
                    seen.append((obj_id, T_gt, None))
                    continue
                T_est = est[pairs[i]]
                seen.append((obj_id, T_gt, T_est))
                objects.append(ObjectScore(scene_id, im_id, obj_id, 100 * position_error(T_gt, T_est, sym),
                                           rotation_error(T_gt, T_est, sym), 1000 * add_s(T_gt, T_est, points),
                                           is_right(T_gt, T_est, sym), visib_fract=visib[k]))
        if vsd is not None:
            objects = _with_bop(objects, seen, frame, models, vsd)
        out.append(FrameScore(scene_id, im_id, objects, len(mine) - matched - extra, modes, categories.get(scene_id)))
    return out


def _with_bop(objects: list[ObjectScore], seen: list[tuple], frame, models: dict, config: VSDConfig
              ) -> list[ObjectScore]:
    """``objects`` of one frame scored as BOP 2019 scores them: their VSD against its depth image, and their MSSD
    and MSPD; ``seen`` (obj_id, T_gt, T_est or None) per object, in the same order."""
    ids = sorted({obj_id for obj_id, _, _ in seen})
    results = frame_vsd(frame.depth, frame.camera.K, [models[i][2] for i in ids], [models[i][3] for i in ids],
                        [(ids.index(obj_id), T_gt, T_est) for obj_id, T_gt, T_est in seen], config)
    width = frame.depth.shape[1]
    out = []
    for o, v, (obj_id, T_gt, T_est) in zip(objects, results, seen):
        o = replace(o, vsd=v.error, vsd_right=v.right, ar_vsd=v.ar)
        if T_est is None:
            out.append(replace(o, ar_mssd=0.0, ar_mspd=0.0))
            continue
        _, _, mesh, size, symmetries = models[obj_id]
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        e_mssd = mssd(T_gt, T_est, vertices, symmetries)
        e_mspd = ar.mspd(T_gt, T_est, vertices, frame.camera.K, symmetries)
        out.append(replace(o, mssd_mm=1000 * e_mssd, mspd_px=e_mspd, ar_mssd=ar.ar_mssd(e_mssd, size),
                           ar_mspd=ar.ar_mspd(e_mspd, width)))
    return out


def summary(frames: list[FrameScore], vsd: VSDConfig = VSDConfig()) -> dict:
    """The counts the report's summary gives, for ``score --json``: objects and frames right within 2 cm and
    10 degrees, and (when scored, with ``vsd`` the settings they were scored with) objects VSD-right and AR_VSD,
    the mean over objects of their share of AR_VSD's (tau, theta) pairs (an object without an estimate counts 0:
    BOP's recall over every ground-truth instance), AR_MSSD and AR_MSPD likewise, and AR, the mean of the three.
    Where the dataset gives visibilities: the same counts over the objects seen (``visible``: BOP's test targets)
    and the hidden ones (``hidden``). In sets with scenes.json: ``categories``, per category the object counts, all,
    seen and hidden."""
    objects = [o for f in frames for o in f.objects]
    out = {"frames": len(frames), "frames_right": sum(f.right for f in frames), **_counts(objects),
           "right_cm": RIGHT_CM, "right_deg": RIGHT_DEG}
    if "vsd_right" in out:
        recalls = {key: float(np.mean([getattr(o, key) for o in objects])) for key in ("ar_vsd", "ar_mssd", "ar_mspd")}
        out.update(ar=float(np.mean(list(recalls.values()))), **recalls, vsd_tau_mm=1000 * vsd.tau,
                   vsd_theta=vsd.theta, vsd_delta_mm=1000 * vsd.delta)
    if any(np.isfinite(o.visib_fract) for o in objects):
        out.update(hidden_visib=HIDDEN_VISIB, **_counts_by_visibility(objects))
    categories = list(dict.fromkeys(f.category for f in frames if f.category is not None))
    if categories:
        out["categories"] = {}
        for c in categories:
            mine = [o for f in frames if f.category == c for o in f.objects]
            out["categories"][c] = {**_counts(mine), **_counts_by_visibility(mine)}
    return out


def _counts(objects: list[ObjectScore]) -> dict:
    """{"objects", "objects_right"} and, when every one was scored by VSD, "vsd_right"."""
    out = {"objects": len(objects), "objects_right": sum(o.right for o in objects)}
    if objects and all(o.vsd_right is not None for o in objects):
        out["vsd_right"] = sum(o.vsd_right for o in objects)
    return out


def _counts_by_visibility(objects: list[ObjectScore]) -> dict:
    """{"visible": ``_counts`` of the objects at least ``HIDDEN_VISIB`` visible, "hidden": of the others}."""
    return {"visible": _counts([o for o in objects if not o.hidden]),
            "hidden": _counts([o for o in objects if o.hidden])}


def _count_text(c: dict) -> str:
    """"right/objects" and, when scored, ", VSD vsd_right"."""
    return f"{c['objects_right']}/{c['objects']}" + (f", VSD {c['vsd_right']}" if "vsd_right" in c else "")


def report(frames: list[FrameScore], vsd: VSDConfig = VSDConfig()) -> list[str]:
    """Lines for the terminal: one per object, then the summary (VSD's, when scored with ``vsd``)."""
    lines = ["scene  image  obj  position_cm  rotation_deg  add_s_mm  right"]
    for f in frames:
        for o in f.objects:
            if o.estimated:
                lines.append(f"{o.scene_id:5d}  {o.im_id:5d}  {o.obj_id:3d}  {o.position_cm:11.2f}  "
                             f"{o.rotation_deg:12.1f}  {o.add_s_mm:8.1f}  {'yes' if o.right else 'no'}")
            else:
                lines.append(f"{o.scene_id:5d}  {o.im_id:5d}  {o.obj_id:3d}  {'no estimate':>11s}")
    objects = [o for f in frames for o in f.objects]
    estimated = [o for o in objects if o.estimated]
    lines.append(f"# {len(frames)} frame(s): {sum(f.right for f in frames)} with every object right; "
                 f"{sum(o.right for o in objects)}/{len(objects)} objects right (within {RIGHT_CM:g} cm and "
                 f"{RIGHT_DEG:g} deg, up to the models' symmetries)")
    if estimated:
        lines.append(f"# median position error {np.median([o.position_cm for o in estimated]):.2f} cm, median "
                     f"rotation error {np.median([o.rotation_deg for o in estimated]):.1f} deg, median ADD-S "
                     f"{np.median([o.add_s_mm for o in estimated]):.1f} mm")
    totals = summary(frames, vsd)
    if "vsd_right" in totals:
        lines.append(f"# {totals['vsd_right']}/{len(objects)} objects right by BOP's visible surface discrepancy "
                     f"(VSD < {totals['vsd_theta']:g} at tau {totals['vsd_tau_mm']:g} mm, delta "
                     f"{totals['vsd_delta_mm']:g} mm); AR_VSD {totals['ar_vsd']:.3f}")
        lines.append(f"# BOP 2019 average recall AR {totals['ar']:.3f} = mean of AR_VSD {totals['ar_vsd']:.3f}, "
                     f"AR_MSSD {totals['ar_mssd']:.3f} and AR_MSPD {totals['ar_mspd']:.3f}")
        differ = [o for o in objects if o.estimated and o.vsd_right != o.right]
        if differ:  # what VSD forgives (a hidden part) or catches that the pose tolerances do not
            lines.append("# VSD and 2 cm/10 deg differ on " + ", ".join(
                f"scene {o.scene_id} image {o.im_id} obj {o.obj_id} (VSD {o.vsd:.2f}: "
                f"{'right' if o.vsd_right else 'wrong'})" for o in differ))
    if totals.get("hidden", {}).get("objects"):  # BOP's targets: objects at least HIDDEN_VISIB visible
        lines.append(f"# of the objects at least {HIDDEN_VISIB:.0%} visible (BOP's test targets): "
                     f"{_count_text(totals['visible'])}; of the {totals['hidden']['objects']} hidden ones, "
                     f"which the depth hardly constrains: {_count_text(totals['hidden'])}")
    if "categories" in totals:
        lines.append("# per category, right/objects (objects under "
                     f"{HIDDEN_VISIB:.0%} visible apart): " + "; ".join(
                         f"{c} {_count_text(n['visible'])}" + (f" + hidden {_count_text(n['hidden'])}"
                                                               if n["hidden"]["objects"] else "")
                         for c, n in totals["categories"].items()))
    modes = [m for f in frames for m in f.modes]
    if any(len(m.probabilities) > 1 for m in modes):  # a posterior: several rows per object, scored by probability
        lines.append(f"# posterior ({len(modes)} objects): top-1 {calibration.top1(modes):.3f}, the truth among the "
                     f"modes holding 95 % {calibration.coverage(modes):.3f}, expected calibration error of the top "
                     f"mode {calibration.expected_calibration_error(modes):.3f}")
    missing = len(objects) - len(estimated)
    extra = sum(f.unmatched_rows for f in frames)
    if missing or extra:
        lines.append(f"# {missing} object(s) without an estimate, {extra} estimate row(s) without a ground-truth "
                     "object")
    return lines
