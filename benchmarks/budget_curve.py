"""Accuracy against the anytime budget (`workbench estimate --budget`): every frame of a dataset estimated at each
budget, then scored as a user would (`workbench score --json`): objects right, frames right, BOP's AR, and the median
wall time per frame (from the results CSV's `time` column: the frame's whole time, loading included). Writes a
markdown table and a PNG plot (AR and the share of objects right against the budget, log scale; the unlimited run
at the right).

    .venv/bin/python benchmarks/budget_curve.py ../shared/datasets/ycbv-real-dev --out bench-out/budget \
        [--budgets 1,2,4,8,16,32,none] [--seed 0]

Run it with nothing else on the machine: the budget is wall time, so a loaded machine gets less done by it.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw


def run(cmd: list[str]) -> None:
    print("$ " + " ".join(cmd), file=sys.stderr, flush=True)
    subprocess.run(cmd, check=True)


def frame_times(results: Path) -> list[float]:
    """Each frame's wall seconds (the `time` column, one value per frame)."""
    with open(results, newline="") as f:
        return list({(r["scene_id"], r["im_id"]): float(r["time"]) for r in csv.DictReader(f)}.values())


def measure(dataset: Path, out: Path, budget: float | None, seed: int) -> dict:
    """One budget: estimate, score -> its row."""
    name = "unlimited" if budget is None else f"{budget:g}s"
    results, scores = out / f"results-{name}.csv", out / f"score-{name}.json"
    cmd = [sys.executable, "-m", "workbench.cli", "estimate", str(dataset), "--seed", str(seed), "--out",
           str(results), "--force"]
    run(cmd + ([] if budget is None else ["--budget", f"{budget:g}"]))
    run([sys.executable, "-m", "workbench.cli", "score", str(dataset), str(results), "--json", str(scores),
         "--force"])
    s = json.loads(scores.read_text())["summary"]
    times = frame_times(results)
    return {"budget": budget, "objects": s["objects"], "objects_right": s["objects_right"], "frames": s["frames"],
            "frames_right": s["frames_right"], "vsd_right": s.get("vsd_right"), "ar": s.get("ar", float("nan")),
            "median_s": float(np.median(times)), "max_s": float(np.max(times))}


def table(rows: list[dict]) -> list[str]:
    lines = ["| budget | objects right | frames right | VSD right | AR | median s per frame | slowest frame s |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        b = "unlimited" if r["budget"] is None else f"{r['budget']:g} s"
        lines.append(f"| {b} | {r['objects_right']}/{r['objects']} | {r['frames_right']}/{r['frames']} "
                     f"| {r['vsd_right']} | {r['ar']:.3f} | {r['median_s']:.1f} | {r['max_s']:.1f} |")
    return lines


def plot(rows: list[dict], path: Path, title: str) -> None:
    """AR (red) and the share of objects right (blue) against the budget, log scale; the unlimited run drawn at
    the right edge, its median time written beside it."""
    width, height, left, right, top, bottom = 640, 400, 60, 110, 40, 50
    image = Image.new("RGB", (width, height), "white")
    draw = ImageDraw.Draw(image)
    finite = [r for r in rows if r["budget"] is not None]
    lo, hi = math.log2(min(r["budget"] for r in finite)), math.log2(max(r["budget"] for r in finite))
    span_x = width - left - right

    def x_of(b: float | None) -> float:
        return width - right + 50 if b is None else left + (math.log2(b) - lo) / max(hi - lo, 1e-9) * span_x

    def y_of(v: float) -> float:
        return top + (1 - v) * (height - top - bottom)

    draw.rectangle([left, top, width - right, height - bottom], outline="black")
    for v in np.linspace(0, 1, 6):
        draw.line([left, y_of(v), width - right, y_of(v)], fill=(230, 230, 230))
        draw.text((left - 30, y_of(v) - 6), f"{v:.1f}", fill="black")
    for r in rows:
        label = "none" if r["budget"] is None else f"{r['budget']:g}"
        draw.text((x_of(r["budget"]) - 8, height - bottom + 6), label, fill="black")
    series = [("AR", lambda r: r["ar"], (200, 50, 40)),
              ("objects right", lambda r: r["objects_right"] / r["objects"], (40, 90, 200))]
    for name, value, colour in series:
        pts = [(x_of(r["budget"]), y_of(value(r))) for r in finite]
        draw.line(pts, fill=colour, width=2)
        for r in rows:
            x, y = x_of(r["budget"]), y_of(value(r))
            draw.ellipse([x - 4, y - 4, x + 4, y + 4], fill=colour)
    draw.text((left, 12), title, fill="black")
    draw.text((left + span_x / 2 - 80, height - 22), "budget per frame, s (log scale)", fill="black")
    for i, (name, _, colour) in enumerate(series):
        draw.rectangle([left + 10, top + 10 + 18 * i, left + 22, top + 22 + 18 * i], fill=colour)
        draw.text((left + 28, top + 10 + 18 * i), name, fill="black")
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--out", type=Path, default=Path("bench-out/budget"))
    parser.add_argument("--budgets", default="1,2,4,8,16,32,none")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    budgets = [None if b.strip() == "none" else float(b) for b in args.budgets.split(",")]
    rows = [measure(args.dataset, args.out, b, args.seed) for b in budgets]
    lines = table(rows)
    (args.out / "budget.md").write_text("\n".join(lines) + "\n")
    (args.out / "budget.json").write_text(json.dumps(rows, indent=1) + "\n")
    plot(rows, args.out / "budget.png", f"{args.dataset.name}: accuracy against the budget (seed {args.seed})")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
