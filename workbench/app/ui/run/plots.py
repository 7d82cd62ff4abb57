"""Plots over iterations with viser's uPlot, one chart per question a researcher asks of a run:

- **log-likelihood**: the best and mean particle's, and the dataset's truth's and the labels' as two levels where
  known (the estimate should reach them; above them means the likelihood prefers a wrong scene);
- **tempering exponent β**: how much of the raw likelihood the weights use (the effective sample size is held at
  a fixed share of N by choosing β, so ESS itself says nothing);
- **distinct particles after resampling**: how many different particles the resampling keeps (few: collapse);
- **acceptance** (PI-MCPF only): the accepted share of proposals, per move kind where the report carries ``moves``
  (``{kind: {"proposed": n, "accepted": m}}``);
- **best particle's move / convergence threshold** (log scale): below 1 on both curves = calm.

Every chart spans the same iterations, from 0 to the latest (one x-axis, labelled "iteration").

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

from workbench.app.ui.ui_thread import UiThread
from workbench.app.ui.widgets.layout import without_number_box

HEIGHT = 140  # px per chart; the tab's "Plot height" slider changes it (100 to 400)
# The popped-out window at first (x, y, width, height in CSS px: left of the panel, clear of it from a window 1000 px
# wide; the user moves and resizes it) and the least chart height in it.
POP_OUT = (16.0, 16.0, 560.0, 660.0)
POP_OUT_HEIGHT = 220
# Iterations, not timestamps (uPlot's default x scale is time); every chart spans the same iterations (one shared
# x-axis, labelled on each); room for numbers like -20,000 on the y axis.
X_AXIS: uplot.Axis = {"label": "iteration", "labelSize": 16, "size": 34,
                       "incrs": (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000)}  # whole iterations only
AXES: tuple[uplot.Axis, ...] = (X_AXIS, {"size": 64})
NO_LEGEND: uplot.Legend = {"show": False}
MOVE_COLORS = ("#1c7ed6", "#e8590c", "#2f9e44", "#ae3ec9", "#f59f00", "#0c8599", "#868e96")
TRUTH_COLOR = "#212529"  # the ground truth's level: near-black as its outline in the 3D view
LABEL_LEVEL_COLOR = "#c2255c"  # the labels' level: magenta as their outline


FLOOR_COLOR = "#868e96"  # the level of the best scene before the clutter floor was weighed in


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


LEVELS = (("truth_loglik", "truth", TRUTH_COLOR), ("label_loglik", "labels", LABEL_LEVEL_COLOR))


def _levels(reports: list[dict]) -> list[tuple[str, str, str]]:
    """The known scenes' levels the reports carry a value for: the dataset's truth and the labels, apart."""
    return [lv for lv in LEVELS if np.isfinite(column(reports, lv[0])).any()]


def floor_level(reports: list[dict]) -> tuple[int, float] | None:
    """Where the clutter floor was weighed in: (the first iteration with it, after one without it; the best
    log-likelihood of the iteration before), None where the run has no such step. The log-likelihood jumps there:
    every scene's unexplained readings start to score the floor."""
    for i in range(1, len(reports)):
        before = reports[i - 1].get("best_loglik")
        if reports[i].get("floor_in", True) and not reports[i - 1].get("floor_in", True) and before is not None \
                and np.isfinite(before):
            return int(reports[i]["iteration"]), float(before)
    return None


def _loglik_lines(reports: list[dict]) -> tuple[Line, ...]:
    extra = tuple(Line(label, color, dashed=True) for _, label, color in _levels(reports))
    floor = floor_level(reports)
    # The jump marked as a level: where the best stood before the floor counted, named with the iteration it did
    # (uPlot takes no gaps here: a NaN breaks its auto-range, so a marker at one iteration cannot be drawn).
    if floor is not None:
        extra += (Line(f"best before the clutter floor (in from iteration {floor[0]})", FLOOR_COLOR, True),)
    return (Line("best", "#e8590c"), Line("mean", "#1c7ed6"), *extra)


def _loglik_columns(reports: list[dict], ctx: dict) -> tuple[np.ndarray, ...] | None:
    it = column(reports, "iteration")
    best, mean = column(reports, "best_loglik"), column(reports, "mean_loglik")
    # Each known scene as a level across the whole run: its latest value (labels can change during a run).
    levels = []
    for key, _, _ in _levels(reports):
        ref = column(reports, key)
        levels.append(np.full_like(it, ref[np.isfinite(ref)][-1]))
    floor = floor_level(reports)
    if floor is not None:
        levels.append(np.full_like(it, floor[1]))
    return finite_rows(it, best, mean, *levels)


def _beta_columns(reports: list[dict], ctx: dict) -> tuple[np.ndarray, ...] | None:
    it, beta = column(reports, "iteration"), column(reports, "beta")
    beta = np.where(beta > 0, beta, np.nan)  # a log scale: zero or less has no place on it
    return finite_rows(it, beta)


def _distinct_columns(reports: list[dict], ctx: dict) -> tuple[np.ndarray, ...] | None:
    distinct = column(reports, "distinct_after_resampling")
    n = np.array(ctx["particles"], dtype=np.float64)
    return finite_rows(column(reports, "iteration"), distinct, n)


def _acceptance_series(reports: list[dict]) -> list[tuple[Line, np.ndarray]]:
    """The overall acceptance (PI-MCPF's ``accept_rate``) and one per move kind, each only where it has values;
    nothing where nothing is accepted or rejected (PI-PF, whose per-kind counts are expected offspring)."""
    overall = column(reports, "accept_rate")
    if not np.isfinite(overall).any():
        return []
    out = [(Line("all", "#495057"), overall)]
    out += [(Line(k, MOVE_COLORS[i % len(MOVE_COLORS)]), acceptance(reports, k))
            for i, k in enumerate(move_kinds(reports))]
    return [(line, y) for line, y in out if np.isfinite(y).any()]


def _acceptance_columns(reports: list[dict], ctx: dict) -> tuple[np.ndarray, ...] | None:
    series = _acceptance_series(reports)
    if not series:
        return None  # PI-PF without move kinds: nothing is accepted or rejected
    return finite_rows(column(reports, "iteration"), *(y for _, y in series))


MOVE_FLOOR = 1e-3  # a log scale has no zero: a move of nothing is drawn at this ratio


def _move_columns(reports: list[dict], ctx: dict) -> tuple[np.ndarray, ...] | None:
    x, dm, dd = finite_rows(column(reports, "iteration"), column(reports, "best_move_m") / ctx["converge_m"],
                           column(reports, "best_move_deg") / ctx["converge_deg"])
    return x, np.maximum(dm, MOVE_FLOOR), np.maximum(dd, MOVE_FLOOR), np.ones_like(x)


CHARTS: tuple[Chart, ...] = (
    Chart("loglik", "log-likelihood", _loglik_lines, _loglik_columns),
    Chart("beta", "tempering exponent β", lambda r: (Line("β", "#2f9e44"),), _beta_columns,
          y_scale={"auto": True, "distr": 3}, note="log scale; weights ∝ exp(β · log-lik)"),
    Chart("distinct", "distinct particles after resampling",
          lambda r: (Line("distinct (expected)", "#0c8599"), Line("N", "#868e96", dashed=True)), _distinct_columns,
          y_scale={"auto": True, "range": (0.0, None)}),
    Chart("acceptance", "accepted share (PI-MCPF)", lambda r: tuple(ln for ln, _ in _acceptance_series(r)),
          _acceptance_columns,
          y_scale={"auto": False, "range": (0.0, 1.0)}),
    Chart("move", "best's move / convergence threshold",
          lambda r: (Line("position", "#ae3ec9"), Line("angle", "#f59f00"), Line("rule", "#495057", dashed=True)),
          _move_columns, y_scale={"auto": True, "distr": 3}, note="log scale; below 1 on both = calm"),
)


def legend_html(chart: Chart, lines: tuple[Line, ...]) -> str:
    """The chart's title and a colour swatch per line, as one line of HTML."""
    return header_html(chart.title, lines, chart.note)


def header_html(title: str, lines: tuple[Line, ...], note: str = "") -> str:
    """A chart's ``title``, its ``note`` and a colour swatch per line, as one line of HTML."""
    swatches = " ".join(
        f'<span style="white-space:nowrap"><span style="display:inline-block;width:14px;height:0;'
        f'border-top:2px {"dashed" if ln.dashed else "solid"} {ln.color};vertical-align:middle"></span> '
        f"{ln.label}</span>"
        for ln in lines
    )
    note = f' <span style="opacity:0.6">· {note}</span>' if note else ""
    return f'<div style="font-size:0.8em;padding:0.3em 0.5em 0"><b>{title}</b>{note}<br>{swatches}</div>'


@dataclass
class Drawn:
    lines: tuple[Line, ...]
    header: viser.GuiHtmlHandle
    plot: viser.GuiUplotHandle


@dataclass
class Plots:
    """The Plots tab: its charts over the run's reports (dicts of ``IterationReport.as_dict()``, plus what the
    engine adds: ``distinct_after_resampling``, ``truth_loglik`` and ``label_loglik``). *Pop out* moves the charts
    into a window of their own (``viser`` panel: the user moves, docks and resizes it; the charts follow its width),
    *Put back* returns them to the tab; every browser tab sees the same place, as it sees the same run."""

    gui: viser.GuiApi
    tab: viser.GuiTabHandle
    ui: UiThread
    reports: list[dict] = field(default_factory=list)
    particles: list[int] = field(default_factory=list)
    drawn: dict[str, Drawn] = field(default_factory=dict)
    context: dict = field(default_factory=lambda: {"converge_m": 0.01, "converge_deg": 3.0})

    height: int = HEIGHT

    def __post_init__(self) -> None:
        self.window: viser.PanelHandle | None = None  # the popped-out window, while there is one
        self.docked_height = HEIGHT  # the charts' height in the tab, given back when they come back
        self.container: viser.GuiTabHandle = self.tab  # where the charts are drawn
        with self.tab:
            self.size = self.gui.add_slider("Plot height", 100, 400, 20, HEIGHT, order=-2.0,
                                            hint="px per chart: taller charts, or more of them on screen")
            without_number_box(self.gui, self.size)
            self.pop = self.gui.add_button("Pop out", icon=viser.Icon.ARROWS_MAXIMIZE, order=-1.0,
                                           hint="the charts in a window of their own: move it, dock it, resize it")
            self.away = self.gui.add_markdown("The charts are in their own window.", order=-0.5, visible=False)
            self.back = self.gui.add_button("Put back", icon=viser.Icon.ARROWS_MINIMIZE, order=-0.4, visible=False)
            self.empty = self.gui.add_markdown("No iterations yet: **Step** or **Run** draws the plots here.",
                                               order=0.0)
        self.size.on_update(self.ui.callback(lambda _: self.resize(int(self.size.value))))
        self.pop.on_click(self.ui.callback(lambda _: self.pop_out()))
        self.back.on_click(self.ui.callback(lambda _: self.put_back()))

    def pop_out(self) -> None:
        """Draw the charts in a floating window (``POP_OUT`` px at first), taller (``POP_OUT_HEIGHT`` at least)."""
        if self.window is not None:
            return
        self.window = self.gui.add_panel()
        self.container = self.window.add_tab("Plots", viser.Icon.CHART_LINE)
        with self.container:
            put_back = self.gui.add_button("Put back", icon=viser.Icon.ARROWS_MINIMIZE, order=-1.0,
                                           hint="the charts back into the panel's Plots tab")
        put_back.on_click(self.ui.callback(lambda _: self.put_back()))
        x, y, width, height = POP_OUT
        self.window.float(x=x, y=y, width=width, height=height)
        self.pop.visible, self.away.visible, self.back.visible = False, True, True
        self.docked_height = int(self.size.value)
        self.size.value = max(self.docked_height, POP_OUT_HEIGHT)
        self.resize(int(self.size.value))

    def put_back(self) -> None:
        """The charts back in the Plots tab, at the height they had before the window."""
        if self.window is None:
            return
        self.window.remove()  # and the charts in it
        self.window, self.container, self.drawn = None, self.tab, {}
        self.pop.visible, self.away.visible, self.back.visible = True, False, False
        self.size.value = self.docked_height
        self.resize(self.docked_height)

    def resize(self, height: int) -> None:
        """Every chart ``height`` px tall (re-created: uPlot takes its size when made)."""
        self.height = height
        self._remove_charts()
        if self.reports:
            self.redraw(self.context.get("converge_m", 0.01), self.context.get("converge_deg", 3.0))

    def _remove_charts(self) -> None:
        for d in self.drawn.values():
            d.header.remove()
            d.plot.remove()
        self.drawn = {}

    def clear(self) -> None:
        self.reports, self.particles = [], []
        self._remove_charts()
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
                d.plot.scales = self.scales(chart)
        self.empty.visible = not self.drawn

    def scales(self, chart: Chart) -> dict:
        """One x range for every chart: the run's iterations so far, from 0."""
        last = max((r["iteration"] for r in self.reports), default=0)
        return {"x": {"time": False, "auto": False, "range": (0.0, float(max(1, last)))}, "y": chart.y_scale}

    def _create(self, i: int, chart: Chart, lines: tuple[Line, ...], data: tuple[np.ndarray, ...]) -> Drawn:
        with self.container:
            header = self.gui.add_html(legend_html(chart, lines), order=10.0 * (i + 1))
            plot = self.gui.add_uplot(
                data, ({"label": "iteration"}, *(ln.series() for ln in lines)), height=self.height,
                scales=self.scales(chart), axes=AXES, legend=NO_LEGEND,
                order=10.0 * (i + 1) + 1.0,
            )
        return Drawn(lines, header, plot)
