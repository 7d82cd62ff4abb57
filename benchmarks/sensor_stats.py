"""How a depth sensor errs, measured on BOP frames with ground truth: the true scene's depth is rendered (the
objects at their annotated poses, full meshes, ``score.vsd.render_alone``) and the table's plane fitted to the
observed depth; the observation is compared with that reference on the objects' and the table's pixels.

    PYTHONPATH=. .venv/bin/python benchmarks/sensor_stats.py ../shared/datasets/ycbv-real-dev [MORE ...]
        [--json OUT.json] [--png OUT.png] [--frames N]

Per dataset: the residual's robust std (1.4826 MAD) and share beyond 3 robust stds, on objects and table, and by
reference depth and angle of incidence; its correlation length (lag where its autocorrelation falls to 1/e, in
pixels and in milliradians, which do not depend on the focal length); the share of missing readings at depth
edges, at grazing angles and elsewhere; flying pixels at silhouettes; the per-frame bias (median of observed -
rendered over every object pixel of a frame). With two or more datasets it also prints each statistic's relative
difference from the first one's (|other - first| / |first|).

Choices, and why:
- The table is the dominant plane of the observed depth off the rendered objects (RANSAC, 1 cm, then least
  squares on its inliers): YCB-Video frames carry no table pose, and clutter beside the objects is not modelled.
  Its pixels are the readings within 2 cm of the plane, and the holes among them (a missing pixel with at least
  half of its 7x7 window on the table); everything else off the objects is unknown and left out.
- Object pixels within ``EDGE_MRAD`` of a silhouette and residuals beyond 3 cm (an unmodelled occluder, a pose far
  off) are left out of the residual statistics; each object's and the table's residual has its affine ramp removed
  (``detrend``) before the autocorrelation, since annotated poses are good to a few millimetres only.
- Widths are angles (milliradians), turned into pixels with each frame's focal length: YCB-Video's depth is
  registered to its colour camera (fx 1067 px at 640 wide), generated frames use 525 px.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from workbench.geometry import backproject
from workbench.io import bop
from workbench.problem.support import ransac_plane
from workbench.score.vsd import render_alone
from workbench.synth.sensor import stats as st

EDGE_JUMP = 0.02  # m: a reference jump this large is a silhouette (objects stand 3-20 cm above the table)
EDGE_MRAD = 3.0  # the edge band: within this angle of a silhouette (3 px at fx 1067, 1.6 px at 525)
FLY_MRAD = 5.0  # flying pixels: nearest and farthest reference depth within this angle
FLY_MARGIN = 0.005  # m: a flying reading is this far from both sides at least (~3 sigma of the noise at 1 m)
GRAZING_DEG = 70.0  # beyond this angle of incidence a pixel counts as grazing
OUTLIER = 0.03  # m: residuals beyond are not the sensor's noise (occluder, pose off) and left out
TABLE_BAND = 0.02  # m: readings this close to the plane are the table's
MIN_BIN = 20000  # px: a depth or angle bin with fewer pixels is not reported (a few frames' corner)
MAX_LAG = 40  # px
MAX_LAG_SLOW = 200  # px
SLOW_MRAD = 15.0  # the slow part of a residual: its mean within this angle (16 px at fx 1067, 8 px at 525)
DEPTH_BINS = np.array([0.5, 0.8, 0.95, 1.1, 1.3, 1.6, 2.0])
ANGLE_BINS = np.array([0.0, 30.0, 45.0, 60.0, 70.0, 80.0, 90.0])


def plane_depth(K: np.ndarray, shape: tuple[int, int], n: np.ndarray, d: float) -> np.ndarray:
    """Camera-z depth (H, W) metres of the plane n.p + d = 0 along each pixel's ray; NaN where it lies behind."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(shape)], axis=-1)
    denom = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        z = -d / denom
    return np.where(np.isfinite(z) & (z > 0), z, np.nan)


def box_mean(mask: np.ndarray, radius: int) -> np.ndarray:
    """Share of True in each pixel's (2 radius + 1)^2 window, (H, W) bool -> (H, W) float."""
    return st.box_sum(mask.astype(np.float64), radius) / (2 * radius + 1) ** 2


def fit_table(observed: np.ndarray, K: np.ndarray, off_objects: np.ndarray, seed: int = 0
              ) -> tuple[np.ndarray, float]:
    """The dominant plane (unit normal (3,), offset) of the observed readings off the objects."""
    pts = backproject(observed, K)[off_objects & (observed > 0)]
    rng = np.random.default_rng(seed)
    n, d = ransac_plane(pts, 0.01, 400, rng)
    inl = pts[np.abs(pts @ n + d) < 0.01]
    centre = inl.mean(axis=0)
    n = np.linalg.svd(inl - centre, full_matrices=False)[2][2]
    return n, float(-n @ centre)


def frame_arrays(frame, models: dict) -> dict:
    """The reference depth and the pixel classes of one frame (see the module docstring)."""
    K, h, w = frame.camera.K, frame.camera.height, frame.camera.width
    ids = list(dict.fromkeys(frame.object_ids))
    meshes = [models[i].mesh for i in ids]
    poses = [(ids.index(o), T) for o, T in zip(frame.object_ids, frame.gt_T_cam_obj) if np.isfinite(T).all()]
    alone = render_alone(K, w, h, meshes, poses).astype(np.float64)
    alone[alone <= 0] = np.inf
    obj_depth = alone.min(axis=0)
    obj_index = np.where(np.isfinite(obj_depth), alone.argmin(axis=0), -1)
    obj_depth = np.where(np.isfinite(obj_depth), obj_depth, np.nan)
    obs = frame.depth.astype(np.float64)
    on_obj = obj_index >= 0
    px = lambda mrad: max(1, int(round(mrad * 1e-3 * K[0, 0])))  # noqa: E731
    near_obj = box_mean(on_obj, px(10.0)) > 0  # the plane is fitted well off the objects
    n, d = fit_table(obs, K, ~near_obj)
    plane = plane_depth(K, obs.shape, n, d)
    with np.errstate(invalid="ignore"):
        table_read = ~on_obj & (obs > 0) & (np.abs(obs - plane) < TABLE_BAND)
    # A hole is the table's when table or objects surround it (the shadow strip beside a silhouette is a few px).
    table = table_read | (~on_obj & (obs <= 0) & (box_mean(table_read | on_obj, px(7.0)) >= 0.5)
                          & (box_mean(table_read, px(7.0)) > 0.1) & np.isfinite(plane))
    reference = np.where(on_obj, obj_depth, np.where(table, plane, np.nan))
    return {"obs": obs, "reference": reference, "obj_index": obj_index, "table": table, "K": K,
            "edge": st.edge_band(reference, EDGE_JUMP, px(EDGE_MRAD)), "fly_radius": px(FLY_MRAD),
            "angle": np.degrees(st.incidence_angle(reference, K))}


def frame_samples(a: dict) -> dict:
    """Per-frame pieces of the statistics: residual samples (raw, and split into its slow part, the local mean
    within ``SLOW_MRAD``, and the fast rest) with their depth and angle, autocorrelations, hole and flying counts."""
    obs, ref, edge, angle = a["obs"], a["reference"], a["edge"], a["angle"]
    with np.errstate(invalid="ignore"):
        res = obs - ref
        ok = (obs > 0) & np.isfinite(ref) & ~edge & (np.abs(res) < OUTLIER)
    out = {"objects": {}, "table": {}}
    objects = ok & (a["obj_index"] >= 0)
    # The per-frame bias: all of the frame's object pixels (the table's plane is fitted to the data: no bias).
    out["bias"] = float(np.median(res[objects])) if objects.any() else float("nan")
    slow_px = max(1, int(round(SLOW_MRAD * 1e-3 * a["K"][0, 0])))
    for name, region in (("objects", objects), ("table", ok & a["table"])):
        parts = [region & (a["obj_index"] == k) for k in np.unique(a["obj_index"][objects])] \
            if name == "objects" else [region]
        slow, flat = np.zeros(res.shape), np.zeros(res.shape)
        for p in parts:
            slow += np.where(p, np.nan_to_num(st.local_mean(res, p, slow_px)), 0.0)
            flat += st.detrend(np.where(p, res, 0.0), p)
        fast = res - slow
        o = out[name]
        o["res"], o["fast"], o["z"], o["angle"] = res[region], fast[region], ref[region], angle[region]
        o["fast_z2"] = fast[region] / ref[region] ** 2  # m per m^2: comparable between sets seen from other distances
        o["slow"] = st.detrend(slow, region)[region]  # the plane or the pose leaves a ramp: not the sensor's
        o["acf_fast"] = st.autocorrelation(np.where(region, fast, 0.0), region, MAX_LAG)
        o["acf_slow"] = st.autocorrelation(st.detrend(slow, region), region, MAX_LAG_SLOW)
        o["acf_n"] = int(region.sum())
    expected = np.isfinite(ref)
    grazing = np.nan_to_num(angle, nan=0.0) > GRAZING_DEG
    out["holes"] = {k: st.hole_fractions(obs, expected & sel, edge, grazing)
                    for k, sel in (("objects", a["obj_index"] >= 0), ("table", a["table"]), ("all", expected))}
    out["flying"] = st.flying_fraction(obs, ref, edge & expected, a["fly_radius"], FLY_MARGIN)
    out["focal"] = float(a["K"][0, 0])
    return out


def pooled_acf(samples: list[dict], name: str, key: str) -> np.ndarray:
    """The frames' autocorrelations of region ``name``, weighted by their pixel counts."""
    weights = np.array([x[name]["acf_n"] for x in samples], dtype=np.float64)
    acfs = np.array([x[name][key] for x in samples])
    good = np.isfinite(acfs).all(axis=1) & (weights > 0)
    return (acfs[good] * weights[good, None]).sum(0) / weights[good].sum() if good.any() else acfs[0]


def summarise(samples: list[dict]) -> dict:
    """Pool the frames' pieces into the dataset's statistics (lengths mm, angles degrees, shares in [0, 1])."""
    s: dict = {"frames": len(samples)}
    focal = float(np.mean([x["focal"] for x in samples]))
    mm = lambda bins: [dict(b, robust_std=1e3 * b["robust_std"]) for b in bins]  # noqa: E731
    for name in ("objects", "table"):
        cat = {k: np.concatenate([x[name][k] for x in samples])
               for k in ("res", "fast", "fast_z2", "slow", "z", "angle")}
        acf_fast, acf_slow = pooled_acf(samples, name, "acf_fast"), pooled_acf(samples, name, "acf_slow")
        fast_len, slow_len = st.correlation_length(acf_fast), st.correlation_length(acf_slow)
        s[name] = {"n": int(cat["res"].size), "robust_std_mm": 1e3 * st.robust_std(cat["res"]),
                   "tail3": st.tail_fraction(cat["res"]), "median_z": float(np.median(cat["z"])),
                   "fast_std_mm": 1e3 * st.robust_std(cat["fast"]),
                   "fast_z2_mm": 1e3 * st.robust_std(cat["fast_z2"]), "fast_z2_tail3": st.tail_fraction(cat["fast_z2"]),
                   "slow_std_mm": 1e3 * float(np.std(cat["slow"])),
                   "fast_corr_px": fast_len, "fast_corr_mrad": 1e3 * fast_len / focal,
                   "slow_corr_px": slow_len, "slow_corr_mrad": 1e3 * slow_len / focal,
                   "acf_fast": acf_fast.tolist(), "acf_slow": acf_slow.tolist(),
                   "by_depth": mm(st.binned_spread(cat["res"], cat["z"], DEPTH_BINS)),
                   "fast_by_depth": mm(st.binned_spread(cat["fast"], cat["z"], DEPTH_BINS)),
                   "slow_by_depth": mm(st.binned_spread(cat["slow"], cat["z"], DEPTH_BINS)),
                   "fast_by_angle": mm(st.binned_spread(cat["fast_z2"], np.nan_to_num(cat["angle"], nan=-1.0),
                                                        ANGLE_BINS))}  # fast / z^2, mm per m^2
    for region in ("objects", "table", "all"):
        counts = {}
        for g in ("edge", "grazing", "elsewhere"):
            n = sum(x["holes"][region][f"n_{g}"] for x in samples)
            holes = sum(np.nan_to_num(x["holes"][region][g]) * x["holes"][region][f"n_{g}"] for x in samples)
            counts[g] = float(holes / n) if n else float("nan")
            counts[f"n_{g}"] = int(n)
        s[f"holes_{region}"] = counts
    n_fly = sum(x["flying"][1] for x in samples)
    s["flying"] = float(sum(np.nan_to_num(x["flying"][0]) * x["flying"][1] for x in samples) / max(n_fly, 1))
    bias = np.array([x["bias"] for x in samples])
    s["bias_mm"] = {"median": 1e3 * float(np.nanmedian(bias)), "std": 1e3 * float(np.nanstd(bias)),
                    "frames": (1e3 * bias).round(2).tolist()}
    s["focal_px"] = focal
    return s


def measure(dataset: Path, max_frames: int | None = None) -> dict:
    frames = bop.list_frames(dataset)
    if max_frames:
        frames = frames[:: max(1, len(frames) // max_frames)][:max_frames]
    models: dict = {}
    samples = []
    for scene_id, im_id in frames:
        frame = bop.load_frame(dataset, scene_id, im_id)
        if frame.gt_T_cam_obj is None:
            continue
        missing = [o for o in frame.object_ids if o not in models]
        if missing:
            models.update(bop.load_models(dataset, missing))
        samples.append(frame_samples(frame_arrays(frame, models)))
        print(f"  {dataset.name} {scene_id}/{im_id}", file=sys.stderr)
    return summarise(samples)


def headline(s: dict) -> dict[str, float]:
    """The statistics a sensor model must reproduce, flat (name -> value): lengths mm, shares %, angles mrad.
    Only those that do not depend on how far the camera stands: spreads per depth bin (of at least
    ``MIN_BIN`` pixels) or divided by z^2, lengths as angles, shares."""
    row = {}
    for name in ("objects", "table"):
        o = s[name]
        row[f"{name} fast std / z^2, mm/m^2"] = o["fast_z2_mm"]
        row[f"{name} fast / z^2 tail >3 std %"] = 100 * o["fast_z2_tail3"]
        row[f"{name} fast corr length mrad"] = o["fast_corr_mrad"]
        row[f"{name} slow corr length mrad"] = o["slow_corr_mrad"]
    for key in ("by_depth", "fast_by_depth", "slow_by_depth"):
        for b in s["table"][key]:
            if b["n"] >= MIN_BIN:
                row[f"table {key.replace('by_depth', '')}std mm, z {b['lo']:.2f}-{b['hi']:.2f}"] = b["robust_std"]
    for b in s["objects"]["fast_by_angle"]:
        if b["n"] >= MIN_BIN:
            row[f"objects fast/z^2 mm/m^2, {b['lo']:.0f}-{b['hi']:.0f} deg"] = b["robust_std"]
    for g in ("edge", "grazing", "elsewhere"):
        row[f"holes at {g} %"] = 100 * s["holes_all"][g]
    row["flying pixels at edges %"] = 100 * s["flying"]
    row["frame bias std mm"] = s["bias_mm"]["std"]
    return row


def print_table(names: list[str], stats: list[dict]) -> None:
    rows = [headline(s) for s in stats]
    keys = list(dict.fromkeys(k for r in rows for k in r))
    head = f"{'statistic':38s}" + "".join(f"{n[:18]:>20s}" for n in names)
    if len(names) > 1:
        head += "".join(f"{'rel.diff ' + str(i + 1):>12s}" for i in range(1, len(names)))
    print(head)
    for k in keys:
        vals = [r.get(k, float("nan")) for r in rows]
        line = f"{k:38s}" + "".join(f"{v:20.3f}" for v in vals)
        line += "".join(f"{100 * st.relative_difference(v, vals[0]):11.0f}%" for v in vals[1:])
        print(line)


def plot(names: list[str], stats: list[dict], path: Path) -> None:
    try:
        import matplotlib
    except ImportError:
        print("--png needs matplotlib, which is not installed: no plot written", file=sys.stderr)
        return
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    for name, s in zip(names, stats):
        for region, style in (("objects", "-"), ("table", "--")):
            b = [x for x in s[region]["by_depth"] if x["n"] >= 500]
            ax[0].plot([(x["lo"] + x["hi"]) / 2 for x in b], [x["robust_std"] for x in b], style + "o",
                       label=f"{name} {region}")
            b = [x for x in s[region]["fast_by_angle"] if x["n"] >= 500]
            ax[1].plot([(x["lo"] + x["hi"]) / 2 for x in b], [x["robust_std"] for x in b], style + "o",
                       label=f"{name} {region}")
            lags = np.arange(len(s[region]["acf_fast"])) / s["focal_px"] * 1e3
            ax[2].plot(lags, s[region]["acf_fast"], style, label=f"{name} {region}")
    ax[0].set(xlabel="reference depth (m)", ylabel="robust std (mm)")
    ax[1].set(xlabel="angle of incidence (deg)", ylabel="robust std (mm)")
    ax[2].set(xlabel="lag (mrad)", ylabel="autocorrelation", xlim=(0, 40))
    ax[2].axhline(np.exp(-1), color="grey", lw=0.5)
    for a in ax:
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("datasets", type=Path, nargs="+")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--png", type=Path, default=None)
    p.add_argument("--frames", type=int, default=None, help="at most this many frames per dataset, evenly spread")
    args = p.parse_args()
    names = [d.name for d in args.datasets]
    stats = [measure(d, args.frames) for d in args.datasets]
    print_table(names, stats)
    if args.json:
        args.json.write_text(json.dumps(dict(zip(names, stats)), indent=1) + "\n")
    if args.png:
        plot(names, stats, args.png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
