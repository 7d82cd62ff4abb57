"""Colour maps for depth, height, weights and heatmaps, and the HTML legends that name their ranges.

No matplotlib: a colour map is a few control points interpolated linearly, which is all a legend needs.
"""

from __future__ import annotations

import numpy as np

from workbench.app.ui.widgets.markdown import escape

# Control points sampled from matplotlib's viridis (perceptually uniform, readable in greyscale).
VIRIDIS = np.array(
    [[68, 1, 84], [72, 40, 120], [62, 74, 137], [49, 104, 142], [38, 130, 142],
     [31, 158, 137], [53, 183, 121], [110, 206, 88], [181, 222, 43], [253, 231, 37]],
    dtype=np.float64,
)
# Diverging blue-white-red for signed residuals: white means "explained".
DIVERGING = np.array([[33, 102, 172], [103, 169, 207], [247, 247, 247], [239, 138, 98], [178, 24, 43]], np.float64)
# Particle weights: slate blue (negligible) to saturated orange (heavy). Not white: many faint white particles
# read as a haze over the objects.
WEIGHT = np.array([[120, 135, 170], [255, 190, 110], [240, 100, 20]], dtype=np.float64)
# Per-pixel fit: black-red where the scene explains the pixel badly, fading to the table's quiet grey where it
# explains it well, so the errors stand out and the scene still reads like the observation.
MISFIT = np.array([[25, 10, 45], [125, 30, 95], [215, 65, 50], [240, 160, 70], [205, 205, 210]], dtype=np.float64)
MISSING = np.array([60, 60, 60], dtype=np.uint8)


def apply_map(values: np.ndarray, lo: float, hi: float, stops: np.ndarray = VIRIDIS) -> np.ndarray:
    """(...) values -> (..., 3) uint8, ``lo`` at the first stop and ``hi`` at the last; NaN gets MISSING grey."""
    v = np.asarray(values, dtype=np.float64)
    span = hi - lo if hi > lo else 1.0
    t = np.clip((v - lo) / span, 0.0, 1.0) * (len(stops) - 1)
    t = np.nan_to_num(t, nan=0.0)
    i = np.minimum(t.astype(int), len(stops) - 2)
    f = (t - i)[..., None]
    rgb = stops[i] * (1.0 - f) + stops[i + 1] * f
    out = np.round(rgb).astype(np.uint8)
    out[np.isnan(v)] = MISSING
    return out


def robust_range(values: np.ndarray, low_pct: float = 2.0, high_pct: float = 98.0) -> tuple[float, float]:
    """Percentile range of the finite values, so one outlier pixel does not wash the whole map out."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(v, [low_pct, high_pct])
    return float(lo), float(hi if hi > lo else lo + 1e-6)


def legend_html(title: str, lo: str, hi: str, stops: np.ndarray = VIRIDIS, note: str = "") -> str:
    """A horizontal colour bar with its end labels, for ``gui.add_html``."""
    gradient = ", ".join(f"rgb({int(r)},{int(g)},{int(b)})" for r, g, b in stops)
    extra = f'<div style="opacity:0.7">{note}</div>' if note else ""
    return (
        f'<div style="font-size:0.8em;padding:0 0.5em">'
        f"<div><b>{title}</b></div>"
        f'<div style="height:10px;border-radius:3px;background:linear-gradient(to right, {gradient})"></div>'
        f'<div style="display:flex;justify-content:space-between"><span>{lo}</span><span>{hi}</span></div>'
        f"{extra}</div>"
    )


# Distinct solid colours for objects 0, 1, 2, ... (the best scene, the chosen particle). None of them is the
# label's magenta, the "before physics" red-orange or the ground truth's near-black.
OBJECT_COLORS = [(66, 135, 245), (46, 184, 92), (232, 170, 20), (140, 90, 200), (40, 190, 200), (150, 100, 60)]
BEFORE_COLOR = (235, 90, 60)  # the chosen particle as proposed, before physics
MOVE_COLOR = (255, 60, 60)  # how physics moved each object
LABEL_COLOR = (230, 40, 200)
GROUND_TRUTH_COLOR = (30, 30, 30)
REGION_COLOR = (255, 140, 0)
TABLE_COLOR = (200, 190, 170)
SENSOR_COLOR = (40, 40, 40)


def object_color(k: int) -> tuple[int, int, int]:
    return OBJECT_COLORS[k % len(OBJECT_COLORS)]


def named(k: int, name: str) -> str:
    """Object ``k``'s ``name`` (Markdown, escaped) after a square of its colour in the 3D view: a table's object
    cell, told apart at a glance."""
    r, g, b = object_color(k)
    return (f'<span style="display:inline-block;width:0.7em;height:0.7em;border-radius:2px;margin-right:0.3em;'
            f'vertical-align:-0.05em;background:rgb({r},{g},{b})"></span>{escape(name)}')


GHOST_WHITE = 0.5  # the share of white in another mode's colour: pale, told apart from the solid estimate


def ghost_color(k: int) -> tuple[int, int, int]:
    """Object ``k``'s colour paled towards white: its other modes' outlines."""
    return tuple(int(round(c + (255 - c) * GHOST_WHITE)) for c in object_color(k))


def _swatch(rgb, style: str = "solid") -> str:
    """A small square of colour for a legend row: solid fill, an outline ("wire") or a line ("line")."""
    r, g, b = (int(c) for c in rgb)
    c = f"rgb({r},{g},{b})"
    if style == "wire":
        css = f"border:2px dashed {c}"
    elif style == "line":
        css = f"height:0;border-top:3px solid {c};margin-top:6px"
    else:
        css = f"background:{c}"
    return f'<span style="display:inline-block;width:12px;height:12px;{css};vertical-align:middle"></span>'


def view_legend_html(names: list[str], observation: str, heatmap: str = "",
                     confidences: list[str] | None = None) -> str:
    """The one legend of the 3D view: every colour and glyph it can show, with the objects by name, as a compact
    two-column grid. ``observation``: what the observed points' colours mean; ``heatmap``: a note while a heatmap
    replaces them; ``confidences``: per object what the posterior says of its estimate ("p = 0.84, heading open
    ..."; "" or None: nothing known yet)."""
    weight = ", ".join(f"rgb({int(r)},{int(g)},{int(b)})" for r, g, b in WEIGHT)
    gradient = (f'<span style="display:inline-block;width:12px;height:12px;vertical-align:middle;'
                f'background:linear-gradient(to right, {weight})"></span>')
    notes = list(confidences or []) + [""] * len(names)
    objects = ", ".join(f'<b style="color:rgb{object_color(k)}">{n}</b>'
                        + (f' <span data-confidence="{k}">({notes[k]})</span>' if notes[k] else "")
                        for k, n in enumerate(names)) or "—"
    solid = " ".join(_swatch(object_color(k)) for k in range(len(names))) or _swatch(OBJECT_COLORS[0])
    wide = [(solid, f"most likely scene (and the inspected particle after physics): {objects}")]
    cells = [
        (_swatch(ghost_color(0), "wire"), "another mode of the estimate, with its probability"),
        (gradient, "particles: unlikely → likely"),
        (_swatch(BEFORE_COLOR, "wire"), "inspected, before physics"),
        (_swatch(MOVE_COLOR, "line"), "physics moved it"),
        (_swatch(LABEL_COLOR), "label"),
        (_swatch(GROUND_TRUTH_COLOR, "wire"), "ground truth"),
        (_swatch(REGION_COLOR, "line"), "object region"),
        (_swatch(TABLE_COLOR), "table top"),
        (_swatch(SENSOR_COLOR, "line"), "depth sensor"),
    ]
    wide.append((_swatch((150, 150, 150)), heatmap or f"observed points: {observation}"))

    def cell(swatch: str, text: str, span: bool = False) -> str:
        style = "display:flex;gap:0.4em;align-items:flex-start" + (";grid-column:1 / -1" if span else "")
        return f'<div style="{style}"><span style="flex:none">{swatch}</span><span>{text}</span></div>'

    body = cell(*wide[0], span=True) + "".join(cell(*c) for c in cells) + cell(*wide[1], span=True)
    return (f'<div style="font-size:0.75em;line-height:1.3;padding:0 0.5em;display:grid;'
            f'grid-template-columns:1fr 1fr;column-gap:0.6em;row-gap:0.1em" data-legend="3d-view">{body}</div>')
