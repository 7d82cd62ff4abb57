"""Plots over iterations with viser's uPlot: log-likelihood (best, mean), effective sample size, and the best
particle's move measured against the convergence rule (below 1 on both curves = calm)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import viser
import viser.uplot as uplot

HEIGHT = 150
# Iterations, not timestamps (uPlot's default x scale is time); room for numbers like -20,000 on the y axis.
SCALES: dict[str, uplot.Scale] = {"x": {"time": False, "auto": True}}
AXES: tuple[uplot.Axis, ...] = ({}, {"size": 64})


def _series(label: str, stroke: str, dash: tuple[float, ...] | None = None) -> uplot.Series:
    s: uplot.Series = {"label": label, "stroke": stroke, "width": 2}
    if dash:
        s["dash"] = dash
        s["width"] = 1
    return s


def finite_rows(x: np.ndarray, *ys: np.ndarray) -> tuple[np.ndarray, ...]:
    """Keep the iterations where every series is finite: uPlot's auto-range breaks on NaN and infinities."""
    keep = np.isfinite(x)
    for y in ys:
        keep &= np.isfinite(y)
    return (x[keep], *(y[keep] for y in ys))


@dataclass
class Plots:
    gui: viser.GuiApi
    reports: list[dict] = field(default_factory=list)
    particles: list[int] = field(default_factory=list)

    def __post_init__(self) -> None:
        empty = (np.zeros(0), np.zeros(0), np.zeros(0))
        x_axis: uplot.Series = {"label": "iteration"}
        self.loglik = self.gui.add_uplot(
            empty, (x_axis, _series("best", "#e8590c"), _series("mean", "#1c7ed6")),
            title="log-likelihood", height=HEIGHT, scales=SCALES, axes=AXES,
        )
        self.ess = self.gui.add_uplot(
            empty, (x_axis, _series("ESS", "#2f9e44"), _series("N", "#868e96", (4, 4))),
            title="effective sample size", height=HEIGHT, scales=SCALES, axes=AXES,
        )
        self.move = self.gui.add_uplot(
            (np.zeros(0),) * 4,
            (x_axis, _series("position", "#ae3ec9"), _series("angle", "#f59f00"), _series("rule", "#495057", (4, 4))),
            title="best particle's move / convergence threshold", height=HEIGHT,
            scales={**SCALES, "y": {"auto": True, "range": (0.0, None)}}, axes=AXES,
        )

    def clear(self) -> None:
        self.reports, self.particles = [], []
        self.redraw(0.01, 3.0)

    def add(self, report: dict, n_particles: int, converge_m: float, converge_deg: float) -> None:
        """Append an iteration (or replace the last one, when the engine republishes it)."""
        if self.reports and self.reports[-1]["iteration"] == report["iteration"]:
            self.reports.pop()
            self.particles.pop()
        self.reports.append(report)
        self.particles.append(n_particles)
        self.redraw(converge_m, converge_deg)

    def set_history(self, reports: list[dict], n_particles: int, converge_m: float, converge_deg: float) -> None:
        """A whole run at once (a restored session); the history keeps no per-iteration particle count, so the
        current one stands for all."""
        self.reports = list(reports)
        self.particles = [n_particles] * len(reports)
        self.redraw(converge_m, converge_deg)

    def redraw(self, converge_m: float, converge_deg: float) -> None:
        r = self.reports
        col = lambda key: np.array([row[key] for row in r], dtype=np.float64)  # noqa: E731
        it = col("iteration") if r else np.zeros(0)
        if not r:
            self.loglik.data = (it, it, it)
            self.ess.data = (it, it, it)
            self.move.data = (it, it, it, it)
            return
        self.loglik.data = finite_rows(it, col("best_loglik"), col("mean_loglik"))
        self.ess.data = finite_rows(it, col("ess"), np.array(self.particles, dtype=np.float64))
        x, dm, dd = finite_rows(it, col("best_move_m") / converge_m, col("best_move_deg") / converge_deg)
        self.move.data = (x, dm, dd, np.ones_like(x))
