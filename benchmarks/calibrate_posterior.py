"""Fit the posterior's temperature (inference.answer.posterior.TEMPERATURE) on frames with ground truth.

usage: calibrate_posterior.py DATASET POSTERIOR.json [DATASET POSTERIOR.json ...] [--data OUT.json] [--png OUT.png]
                             [--temperature T]

Each POSTERIOR.json is what `workbench estimate DATASET --posterior POSTERIOR.json` wrote (default settings). For
every object it reads the modes' log-likelihood gaps to the estimate, and marks each mode right or not against the
dataset's scene_gt.json (metrics.is_right: 2 cm, 10 degrees, up to the model's symmetries). Then, for temperatures
on a grid, it recomputes the probabilities (posterior.probabilities) and reports
the negative log-likelihood of the right modes, the expected calibration error of the top mode, coverage (the truth
among the modes holding 95 %) and top-1 accuracy; the temperature of least negative log-likelihood is the fit,
broken down per dataset and (generated sets) category. Then it fits the chance that the truth is among none of the
modes (posterior.ELSEWHERE: a logistic in the share of the estimate the sensor sees through) and reports its own
calibration error, and what the top modes' would be with it folded into them. It also counts how often the truth's
heading lies inside a reported range of headings, how often a hidden object's truth lies in its hiding region (a
place within 2 cm, level), and the posterior sweep's share of the frames' wall time. --data
keeps the gaps and right flags (benchmarks/calibration/), so that the fit can be redone without estimating again;
--png draws the reliability diagram, and the breakdown per dataset and category is printed, at the fitted temperature,
or at --temperature (the one the product uses).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from workbench.inference.answer.hidden import estimate_share
from workbench.inference.answer.posterior import found_probability, probabilities
from workbench.io import bop
from workbench.score.calibration import ObjectModes, coverage, expected_calibration_error, reliability_png, top1
from workbench.score.gt_info import HIDDEN_VISIB, gt_info_path, visib_fractions
from workbench.score.metrics import RIGHT_CM, heading_offset_deg, is_right

GRID = np.geomspace(2.0, 400.0, 60)


def collect(dataset: Path, posterior: Path) -> list[dict]:
    """Per object of every frame in ``posterior``: its modes' gaps, which is the estimate's, which are right."""
    document = json.loads(posterior.read_text())
    scenes_json = dataset / "scenes.json"  # a generated dataset's categories, for the breakdown
    category = ({m["scene_id"]: m["category"] for m in json.loads(scenes_json.read_text())["scenes"]}
                if scenes_json.is_file() else {})
    out = []
    models: dict = {}
    for f in document["frames"]:
        frame = bop.load_frame(dataset, f["scene_id"], f["im_id"])
        seen_through = ([o["seen_through"] for o in f["objects"]] if all("seen_through" in o for o in f["objects"])
                        else estimate_seen_through(dataset, f))  # a JSON written before it was reported
        visib = (visib_fractions(frame) if gt_info_path(frame).is_file()
                 else [None] * len(frame.object_ids))  # a dataset without scene_gt_info.json
        for o, through in zip(f["objects"], seen_through):
            if o["obj_id"] not in models:
                models[o["obj_id"]] = bop.load_models(dataset, [o["obj_id"]])[o["obj_id"]]
            modes = o["modes"]
            poses = [mode_pose(m) for m in modes]
            # With several instances of a model, the instance nearest the estimate is this object's truth.
            nearest = min((j for j, i in enumerate(frame.object_ids) if i == o["obj_id"]),
                          key=lambda j: np.linalg.norm(frame.gt_T_cam_obj[j][:3, 3] - poses[0][:3, 3]))
            truth = frame.gt_T_cam_obj[nearest]
            symmetries = models[o["obj_id"]].symmetries
            out.append({"dataset": dataset.name, "category": category.get(f["scene_id"], "real"),
                        "scene_id": f["scene_id"], "im_id": f["im_id"], "obj_id": o["obj_id"],
                        "gaps": [m["gap"] for m in modes], "estimate": [m["what"] == "the estimate" for m in modes],
                        "right": [bool(is_right(truth, T, symmetries)) for T in poses],
                        "yaw_range_deg": o["yaw_range_deg"],
                        "truth_heading_deg": heading_offset_deg(truth, poses[0], np.array(o["vertical_cam"]),
                                                                symmetries),
                        "frame_seconds": f.get("seconds"), "posterior_seconds": f.get("posterior_seconds"),
                        "seen_through": float(through), "visib_fract": visib[nearest],
                        **hiding_record(o.get("hiding"), truth, np.array(o["vertical_cam"]))})
    return out


def hiding_record(hiding: dict | None, truth: np.ndarray, vertical: np.ndarray) -> dict:
    """A hidden object's region (the posterior JSON's ``hiding``) as record entries: its places' gaps, and whether
    the truth's origin lies level within RIGHT_CM of a place (its heading left open) -> {} for an object without."""
    if not hiding:
        return {}
    d = truth[:3, 3] * 1000.0 - np.asarray(hiding["places_mm"])  # (P, 3) mm
    level = d - np.outer(d @ vertical, vertical)
    return {"hiding_gaps": hiding["gaps"],
            "in_region": bool(np.linalg.norm(level, axis=1).min() < 10.0 * RIGHT_CM)}


def mode_pose(mode: dict) -> np.ndarray:
    """A mode of the posterior JSON (``R`` row-major, ``t`` mm, camera frame) -> T_cam_obj (4, 4), metres."""
    return np.vstack([np.hstack([np.reshape(mode["R"], (3, 3)), np.reshape(mode["t"], (3, 1)) / 1000.0]),
                      [0, 0, 0, 1]])


def estimate_seen_through(dataset: Path, frame_json: dict) -> np.ndarray:
    """Per object of one frame of the posterior JSON (in its order, the problem's), the share of its estimate's
    camera-facing surface that the sensor sees through (``scenepoints.object_badness``, all objects at their
    estimates) -> (K,): high where the search put an object where the depth says there is none."""
    from workbench.inference.search.scenepoints import model_samples, object_badness
    from workbench.problem.build import load_bop_problem
    from workbench.problem.problem import ProblemConfig

    ids = [o["obj_id"] for o in frame_json["objects"]]
    _, problem = load_bop_problem(dataset, frame_json["scene_id"], frame_json["im_id"], None, ids, ProblemConfig())
    T_world_cam = np.linalg.inv(problem.camera.T_cam_world)
    scene = np.stack([T_world_cam @ mode_pose(o["modes"][0]) for o in frame_json["objects"]])
    return object_badness(problem, scene, [model_samples(m.mesh) for m in problem.models])


def modes_at(records: list[dict], temperature: float, elsewhere: tuple[float, float] | None = None
             ) -> list[ObjectModes]:
    """Each record's modes with probabilities at ``temperature``, scaled by the chance that the truth is among them
    (the logistic ``elsewhere`` (intercept, slope) in ``seen_through``) where given; a hidden object's then by the
    chance that the truth lies within 2 cm of its estimate's place (``hidden.estimate_share``)."""
    out = []
    for r in records:
        p = probabilities(np.array(r["gaps"]), temperature)
        if elsewhere is not None and r.get("hiding_gaps"):  # a hidden object's elsewhere: the rest of its region
            p = p * estimate_share(probabilities(np.array(r["hiding_gaps"]), temperature))
        elif elsewhere is not None:
            p = p * found_probability(r["seen_through"], elsewhere)
        order = np.argsort(-p, kind="stable")
        out.append(ObjectModes(p[order], np.array(r["right"])[order]))
    return out


def fit_elsewhere(records: list[dict]) -> tuple[float, float]:
    """The logistic (intercept, slope) of "the truth is among the modes" in the share of the estimate the sensor
    sees through, by maximum likelihood (``posterior.ELSEWHERE``)."""
    from scipy.optimize import minimize

    through = np.array([r["seen_through"] for r in records])
    among = np.array([any(r["right"]) for r in records], dtype=np.float64)

    def nll_of(ab: np.ndarray) -> float:
        z = ab[0] + ab[1] * through
        return float(np.sum(np.logaddexp(0.0, -z) * among + np.logaddexp(0.0, z) * (1.0 - among)))

    return tuple(float(v) for v in minimize(nll_of, np.array([3.0, -20.0]), method="Nelder-Mead").x)


def nll(objects: list[ObjectModes]) -> float:
    """Mean negative log probability of the right modes, over the objects that have one among their modes."""
    held = [float(o.probabilities[o.right].sum()) for o in objects if o.right.any()]
    return float(-np.mean(np.log(np.maximum(held, 1e-12)))) if held else float("nan")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("pairs", nargs="*", help="DATASET POSTERIOR.json, repeated")
    ap.add_argument("--data", type=Path, help="write the gaps and right flags here (JSON)")
    ap.add_argument("--from-data", type=Path, nargs="*", default=[], help="add records saved by --data before")
    ap.add_argument("--png", type=Path, help="the reliability diagram at the fitted temperature (or --temperature)")
    ap.add_argument("--temperature", type=float,
                    help="break the objects down and draw the diagram at this temperature, not the fit")
    a = ap.parse_args(argv)
    if len(a.pairs) % 2:
        ap.error("give DATASET POSTERIOR.json pairs")
    records = [r for p in a.from_data for r in json.loads(p.read_text())]
    for dataset, posterior in zip(a.pairs[::2], a.pairs[1::2]):
        records += collect(Path(dataset), Path(posterior))
    if a.data:
        a.data.parent.mkdir(parents=True, exist_ok=True)
        a.data.write_text(json.dumps(records, indent=0) + "\n")
    print(f"{len(records)} objects; {sum(any(r['right']) for r in records)} with the truth among their modes; "
          f"{sum(len(r['gaps']) > 1 for r in records)} with more than one mode")
    print("temperature  nll     ECE    coverage95  top-1")
    fits = []
    for T in GRID:
        objects = modes_at(records, T)
        fits.append((nll(objects), T))
        if np.isclose(T, GRID[::6]).any():
            print(f"{T:11.1f}  {nll(objects):.4f}  {expected_calibration_error(objects):.3f}  "
                  f"{coverage(objects):10.3f}  {top1(objects):.3f}")
    ranged = [r for r in records if r.get("yaw_range_deg") and r.get("truth_heading_deg") is not None]
    inside = sum(r["yaw_range_deg"][0] <= r["truth_heading_deg"] <= r["yaw_range_deg"][1] for r in ranged)
    print(f"{len(ranged)} objects with a range of headings; the truth's heading inside it for {inside}")
    frames = {(r["dataset"], r["scene_id"], r["im_id"]): (r["frame_seconds"], r["posterior_seconds"])
              for r in records if r.get("frame_seconds")}
    if frames:
        total, sweep = np.array(list(frames.values()), dtype=np.float64).T
        print(f"posterior sweep: {sweep.sum():.0f} s of {total.sum():.0f} s over {len(frames)} frames "
              f"({100 * sweep.sum() / total.sum():.1f} %; at most {100 * np.max(sweep / total):.1f} % of a frame)")
    best = min(fits)[1]
    plain = modes_at(records, best)
    print(f"fit: temperature {best:.1f}: nll {nll(plain):.4f}, ECE {expected_calibration_error(plain):.3f}, "
          f"coverage {coverage(plain):.3f}, top-1 {top1(plain):.3f}")
    # Records saved before the seen-through share was reported (benchmarks/calibration/dev-generated-ycb-207.json)
    # have none: no elsewhere to fit, the rest as before.
    doubt = fit_elsewhere(records) if all("seen_through" in r for r in records) else None
    folded = modes_at(records, best, doubt)
    among = np.array([any(r["right"]) for r in records])
    through = np.array([r.get("seen_through", np.nan) for r in records])
    if doubt is not None:
        found = found_probability(through, doubt)
        # The chance of "found" on its own: a one-mode "posterior" per object, right when the truth is among the modes.
        found_ece = expected_calibration_error([ObjectModes(np.array([p]), np.array([a]))
                                                for p, a in zip(found, among)])
        print(f"fit: elsewhere (intercept, slope) ({doubt[0]:.2f}, {doubt[1]:.1f}) in the share seen through: its "
              f"ECE {found_ece:.3f}; folded into the modes, their top-mode ECE "
              f"{expected_calibration_error(folded):.3f} (without it {expected_calibration_error(plain):.3f})")
    if doubt is not None and among.any() and (~among).any():
        print(f"seen through, median (90th percentile): truth among the modes {np.median(through[among]):.3f} "
              f"({np.percentile(through[among], 90):.3f}), not {np.median(through[~among]):.3f} "
              f"({np.percentile(through[~among], 90):.3f})")
    shown = best if a.temperature is None else a.temperature
    objects = modes_at(records, shown)
    folded = modes_at(records, shown, doubt)
    print(f"at temperature {shown:.1f}, per dataset and category: objects, top-1, coverage95, ECE, ECE with elsewhere "
          f"folded in")
    groups: dict[tuple[str, str], list[int]] = {}
    for i, r in enumerate(records):
        groups.setdefault((r["dataset"], r.get("category", "real")), []).append(i)
    for (name, cat), idx in sorted(groups.items()):
        part = [objects[i] for i in idx]
        print(f"  {name:24s} {cat:14s} {len(part):4d}  {top1(part):.3f}  {coverage(part):.3f}  "
              f"{expected_calibration_error(part):.3f}  {expected_calibration_error([folded[i] for i in idx]):.3f}")
    hidden = [i for i, r in enumerate(records) if r.get("visib_fract") is not None and r["visib_fract"] < HIDDEN_VISIB]
    if hidden:
        part = [objects[i] for i in hidden]
        print(f"  {'objects under 10 % visible':39s} {len(part):4d}  {top1(part):.3f}  {coverage(part):.3f}  "
              f"{expected_calibration_error(part):.3f}  {expected_calibration_error([folded[i] for i in hidden]):.3f}")
        covered = [coverage([objects[i]]) == 1.0 or records[i].get("in_region", False) for i in hidden]
        print(f"  {'':39s} the truth among those modes or, for one the sensor sees none of, in its hiding region: "
              f"{np.mean(covered):.3f}")
    regions = [r for r in records if "in_region" in r]
    if regions:
        print(f"{len(regions)} objects the sensor sees none of, with a hiding region: the truth within {RIGHT_CM:g} cm "
              f"of one of its places for {sum(r['in_region'] for r in regions)}; places per region, median "
              f"{np.median([len(r['hiding_gaps']) for r in regions]):.0f}")
    for name in sorted({r["dataset"] for r in records}):
        idx = [i for i, r in enumerate(records) if r["dataset"] == name]
        print(f"  {name:24s} {'all':14s} {len(idx):4d}  {top1([objects[i] for i in idx]):.3f}  "
              f"{coverage([objects[i] for i in idx]):.3f}  {expected_calibration_error([objects[i] for i in idx]):.3f}"
              f"  {expected_calibration_error([folded[i] for i in idx]):.3f}")
    if a.png:
        reliability_png(objects, a.png, f"temperature {shown:.0f}, {len(objects)} objects")
    return 0


if __name__ == "__main__":
    sys.exit(main())
