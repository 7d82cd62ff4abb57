"""How well the posterior's probabilities are calibrated: for each object, its modes (the rows of a results CSV for
that object, ``score`` = probability) against the ground truth.

- **top-1 accuracy**: the most likely mode is right (``score.metrics.is_right``: within 2 cm and 10 degrees, up to the
  model's symmetries);
- **coverage**: the truth lies among the most likely modes that together hold ``mass`` (95 %) of the probability;
- **expected calibration error** of the top mode's probability: in bins of that probability, the gap between the
  mean probability and the share of objects whose top mode is right, weighted by the bins' sizes;
- **reliability diagram**: those bins drawn, saved as PNG (``reliability_png``).
Shared by `workbench score` and ``benchmarks/calibrate_posterior.py``, which fits the posterior's temperature.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from workbench.score.metrics import is_right


@dataclass(frozen=True)
class ObjectModes:
    """One object of one frame: its modes' probabilities (M,), most likely first, and whether each is right."""

    probabilities: np.ndarray
    right: np.ndarray


def object_modes(T_gt: np.ndarray, modes: list[tuple[float, np.ndarray]], symmetries: np.ndarray) -> ObjectModes:
    """``modes``: (probability, T_cam_obj (4, 4)) of one object's rows; ``T_gt`` (4, 4) its truth, same frame."""
    modes = sorted(modes, key=lambda m: -m[0])
    p = np.array([m[0] for m in modes], dtype=np.float64)
    return ObjectModes(p / p.sum() if p.sum() > 0 else p, np.array([is_right(T_gt, T, symmetries) for _, T in modes]))


def top1(objects: list[ObjectModes]) -> float:
    return float(np.mean([o.right[0] for o in objects])) if objects else float("nan")


def coverage(objects: list[ObjectModes], mass: float = 0.95) -> float:
    """The share of objects whose truth lies among their most likely modes holding ``mass`` of the probability."""
    hits = []
    for o in objects:
        held = np.searchsorted(np.cumsum(o.probabilities), mass - 1e-12) + 1  # modes needed to hold the mass
        hits.append(bool(o.right[:held].any()))
    return float(np.mean(hits)) if hits else float("nan")


def reliability(objects: list[ObjectModes], bins: int = 10) -> list[tuple[float, float, float, int]]:
    """Per bin of the top mode's probability ([0, 0.1), ..., [0.9, 1.0]): (lower edge, mean probability, share
    right, objects); empty bins left out."""
    p = np.array([o.probabilities[0] for o in objects])
    right = np.array([o.right[0] for o in objects], dtype=np.float64)
    which = np.minimum((p * bins).astype(int), bins - 1)
    return [(b / bins, float(p[which == b].mean()), float(right[which == b].mean()), int((which == b).sum()))
            for b in range(bins) if (which == b).any()]


def expected_calibration_error(objects: list[ObjectModes], bins: int = 10) -> float:
    n = len(objects)
    return float(sum(count / n * abs(mean_p - share) for _, mean_p, share, count in reliability(objects, bins))
                 ) if n else float("nan")


def reliability_png(objects: list[ObjectModes], path: Path, title: str = "", bins: int = 10) -> None:
    """The reliability diagram (share right against the top mode's probability, per bin; the diagonal is perfect
    calibration; each bin's dot sized by its objects) as a 480x480 PNG at ``path``."""
    size, margin = 480, 50
    image = Image.new("RGB", (size, size), "white")
    draw = ImageDraw.Draw(image)
    span = size - 2 * margin

    def xy(x: float, y: float) -> tuple[float, float]:
        return margin + x * span, size - margin - y * span

    draw.rectangle([xy(0, 1), xy(1, 0)], outline="black")
    draw.line([xy(0, 0), xy(1, 1)], fill=(160, 160, 160), width=1)
    for t in np.linspace(0, 1, 6):
        draw.text((xy(t, 0)[0] - 8, size - margin + 6), f"{t:.1f}", fill="black")
        draw.text((8, xy(0, t)[1] - 6), f"{t:.1f}", fill="black")
    rows = reliability(objects, bins)
    n = max(sum(c for *_, c in rows), 1)
    for lo, mean_p, share, count in rows:
        draw.rectangle([xy(lo, share), xy(lo + 1.0 / bins, 0)], outline=(70, 110, 200))
        r = 3 + 12 * np.sqrt(count / n)
        x, y = xy(mean_p, share)
        draw.ellipse([x - r, y - r, x + r, y + r], fill=(200, 60, 40))
    draw.text((margin, 12), title or "reliability of the top mode", fill="black")
    draw.text((size / 2 - 70, size - 22), "top mode's probability", fill="black")
    draw.text((margin + 6, margin + 4), "share right", fill="black")
    draw.text((size - margin - 150, size - margin - 18),
              f"ECE {expected_calibration_error(objects, bins):.3f}, {len(objects)} objects", fill="black")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    image.save(path)
