"""Plots over iterations with viser's uPlot, one chart per question a researcher asks of a run:

- **log-likelihood**: the best and mean particle's, and the truth's or the label's where one is known (the
  estimate should reach it; above it means the likelihood prefers a wrong scene);
- **tempering exponent β**: how much of the raw likelihood the weights use (the effective sample size is held at
  a fixed share of N by choosing β, so ESS itself says nothing);
- **distinct particles after resampling**: how many different particles the resampling keeps (few: collapse);
- **acceptance**: PI-MCPF's accepted share of proposals, per move kind where the report carries ``moves``
  (``{kind: {"proposed": n, "accepted": m}}``);
- **best particle's move / convergence threshold**: below 1 on both curves = calm.

Each chart is a ``Chart``: a title, its series and a function from the reports to its columns. Charts are created
when their first point arrives and removed at Reset or a new frame: a uPlot created empty (or while its tab is
hidden) kept a stale, blank state after later data in Chromium. uPlot's own title and legend are off (they wrap
and stack while the panel is still laying out); a line of HTML above each chart names its series instead.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import viser
import viser.uplot as uplot

HEIGHT = 140
# Iterations, not timestamps (uPlot's default x scale is time); room for numbers like -20,000 on the y axis.
X_SCALE: uplot.Scale = {"time": False, "auto": True}
AXES: tuple[uplot.Axis, ...] = ({}, {"size": 64})
NO_LEGEND: uplot.Legend = {"show": False}
MOVE_COLORS = ("#1c7ed6", "#e8590c", "#2f9e44", "#ae3ec9", "#f59f00", "#0c8599", "#868e96")
REFERENCE_COLOR = "#c2255c"


@dataclass(frozen=True)
class Line:
    label: str
    color: str
    dashed: bool = False

    def series(self) -> uplot.Series:
        s: uplot.Series = {"label": self.label, "stroke": self.color, "width": 1 if self.dashed else 2}
        if self.dashed:
            s["dash"] = (4, 4)
        return s


def column(reports: list[dict], key: str) -> np.ndarray:
    """(T,) float64 of ``key`` over the reports, NaN where a report lacks it (e.g. a session's older rows)."""
    return np.array([np.nan if r.get(key) is None else float(r[key]) for r in reports], dtype=np.float64)


def finite_rows(x: np.ndarray, *ys: np.ndarray) -> tuple[np.ndarray, ...]:
    """Keep the iterations where every series is finite: uPlot's auto-range breaks on NaN and infinities."""
    keep = np.isfinite(x)
    for y in ys:
        keep &= np.isfinite(y)
    return (x[keep], *(y[keep] for y in ys))


def move_kinds(reports: list[dict]) -> list[str]:
    """The move kinds named in any report's ``moves``, in order of first appearance."""
    kinds: dict[str, None] = {}
    for r in reports:
        for kind in (r.get("moves") or {}):
            kinds[str(kind)] = None
    return list(kinds)


def acceptance(reports: list[dict], kind: str) -> np.ndarray:
    """(T,) accepted / proposed for one move kind, NaN where it was not proposed."""
    out = np.full(len(reports), np.nan)
    for i, r in enumerate(reports):
        m = (r.get("moves") or {}).get(kind)
        if m and m.get("proposed"):
            out[i] = float(m.get("accepted", 0)) / float(m["proposed"])
    return out


@dataclass(frozen=True)
class Chart:
    """One chart: ``columns(reports, context)`` -> (x, y per line), or None while there is nothing to draw."""

    key: str
    title: str
    lines: Callable[[list[dict]], tuple[Line, ...]]
    columns: Callable[[list[dict], dict], tuple[np.ndarray, ...] | None]
    y_scale: uplot.Scale = field(default_factory=lambda: {"auto": True})
    note: str = ""


def _loglik_lines(reports: list[dict]) -> tuple[Line, ...]:
    kind = next((r["reference"] for r in reversed(reports) if r.get("reference")), None)
    extra = (Line(kind, REFERENCE_COLOR, dashed=True),) if kind else ()
    return (Line("best", "#e8590c"), Line("mean", "#1c7ed6"), *extra)


def _loglik_columns(reports: list[dict], ctx: dict) -> tuple[np.ndarray, ...] | None:
    it = column(reports, "iteration")
    best, mean = column(reports, "best_loglik"), column(reports, "mean_loglik")
    if len(_loglik_lines(reports)) == 3:
        # The reference as a level across the whole run: its latest value (labels can change during a run).
        ref = column(reports, "reference_loglik")
        latest = ref[np.isfinite(ref)][-1]
        return finite_rows(it, best, mean, np.full_like(it, latest))
    return finite_rows(it, best, mean)


def _beta_columns(reports: list[dict], ctx: dict) -> tuple[np.ndarray, ...] | None:
    it, beta = column(reports, "iteration"), column(reports, "beta")
    beta = np.where(beta > 0, beta, np.nan)  # a log scale: zero or less has no place on it
    return finite_rows(it, beta)


def _distinct_columns(reports: list[dict], ctx: dict) -> tuple[np.ndarray, ...] | None:
    distinct = column(reports, "distinct_after_resampling")
    n = np.array(ctx["particles"], dtype=np.float64)
    return finite_rows(column(reports, "iteration"), distinct, n)


def _acceptance_series(reports: list[dict]) -> list[tuple[Line, np.ndarray]]:
    """The overall acceptance (PI-MCPF's ``accept_rate``) and one per move kind, each only where it has values."""
    out = [(Line("all", "#495057"), column(reports, "accept_rate"))]
    out += [(Line(k, MOVE_COLORS[i % len(MOVE_COLORS)]), acceptance(reports, k))
            for i, k in enumerate(move_kinds(reports))]
    return [(line, y) for line, y in out if np.isfinite(y).any()]


def _acceptance_columns(reports: list[dict], ctx: dict) -> tuple[np.ndarray, ...] | None:
    series = _acceptance_series(reports)
    if not series:
        return None  # PI-PF without move kinds: nothing is accepted or rejected
    return finite_rows(column(reports, "iteration"), *(y for _, y in series))


def _move_columns(reports: list[dict], ctx: dict) -> tuple[np.ndarray, ...] | None:
    x, dm, dd = finite_rows(column(reports, "iteration"), column(reports, "best_move_m") / ctx["converge_m"],
                           column(reports, "best_move_deg") / ctx["converge_deg"])
    return x, dm, dd, np.ones_like(x)


CHARTS: tuple[Chart, ...] = (
    Chart("loglik", "log-likelihood", _loglik_lines, _loglik_columns),
    Chart("beta", "tempering exponent β (log scale)", lambda r: (Line("β", "#2f9e44"),), _beta_columns,
          y_scale={"auto": True, "distr": 3}, note="weights ∝ exp(β · log-likelihood)"),
    Chart("distinct", "distinct particles after resampling",
          lambda r: (Line("distinct (expected)", "#0c8599"), Line("N", "#868e96", dashed=True)), _distinct_columns,
          y_scale={"auto": True, "range": (0.0, None)}),
    Chart("acceptance", "accepted share of proposals", lambda r: tuple(ln for ln, _ in _acceptance_series(r)),
          _acceptance_columns,
          y_scale={"auto": False, "range": (0.0, 1.0)}),
    Chart("move", "best particle's move / convergence threshold",
          lambda r: (Line("position", "#ae3ec9"), Line("angle", "#f59f00"), Line("rule", "#495057", dashed=True)),
          _move_columns, y_scale={"auto": True, "range": (0.0, None)}, note="below 1 on both = calm"),
)


def legend_html(chart: Chart, lines: tuple[Line, ...]) -> str:
    """The chart's title and a colour swatch per line, as one line of HTML."""
    swatches = " ".join(
        f'<span style="white-space:nowrap"><span style="display:inline-block;width:14px;height:0;'
        f'border-top:2px {"dashed" if ln.dashed else "solid"} {ln.color};vertical-align:middle"></span> '
        f"{ln.label}</span>"
        for ln in lines
    )
    note = f' <span style="opacity:0.6">· {chart.note}</span>' if chart.note else ""
    return f'<div style="font-size:0.8em;padding:0.3em 0.5em 0"><b>{chart.title}</b>{note}<br>{swatches}</div>'


@dataclass
class Drawn:
    lines: tuple[Line, ...]
    header: viser.GuiHtmlHandle
    plot: viser.GuiUplotHandle


@dataclass
class Plots:
    """The Plots tab: its charts over the run's reports (dicts of ``IterationReport.as_dict()``, plus what the
    engine adds: ``distinct_after_resampling``, ``reference_loglik`` and ``reference``)."""

    gui: viser.GuiApi
    tab: viser.GuiTabHandle
    reports: list[dict] = field(default_factory=list)
    particles: list[int] = field(default_factory=list)
    drawn: dict[str, Drawn] = field(default_factory=dict)
    context: dict = field(default_factory=lambda: {"converge_m": 0.01, "converge_deg": 3.0})

    def __post_init__(self) -> None:
        with self.tab:
            self.empty = self.gui.add_markdown("No iterations yet: **Step** or **Run** draws the plots here.",
                                               order=0.0)

    def clear(self) -> None:
        self.reports, self.particles = [], []
        for d in self.drawn.values():
            d.header.remove()
            d.plot.remove()
        self.drawn = {}
        self.empty.visible = True

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
        self.clear()
        self.reports = list(reports)
        self.particles = [n_particles] * len(reports)
        self.redraw(converge_m, converge_deg)

    def redraw(self, converge_m: float, converge_deg: float) -> None:
        self.context = {"converge_m": converge_m, "converge_deg": converge_deg, "particles": self.particles}
        for i, chart in enumerate(CHARTS):
            data = chart.columns(self.reports, self.context) if self.reports else None
            if data is None or len(data[0]) == 0:
                continue
            lines = chart.lines(self.reports)
            d = self.drawn.get(chart.key)
            if d is not None and d.lines != lines:  # a series came or went (a move kind, a reference)
                d.header.remove()
                d.plot.remove()
                d = None
            if d is None:
                self.drawn[chart.key] = self._create(i, chart, lines, data)
            else:
                d.plot.data = data
        self.empty.visible = not self.drawn

    def _create(self, i: int, chart: Chart, lines: tuple[Line, ...], data: tuple[np.ndarray, ...]) -> Drawn:
        with self.tab:
            header = self.gui.add_html(legend_html(chart, lines), order=10.0 * (i + 1))
            plot = self.gui.add_uplot(
                data, ({"label": "iteration"}, *(ln.series() for ln in lines)), height=HEIGHT,
                scales={"x": X_SCALE, "y": chart.y_scale}, axes=AXES, legend=NO_LEGEND,
                order=10.0 * (i + 1) + 1.0,
            )
        return Drawn(lines, header, plot)
