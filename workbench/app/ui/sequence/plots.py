"""Plots across the frames of a sequence, one line per object in its colour: where each object's answer stands in
the sequence's table frame (x, y and height, cm: a static object keeps a flat line while the camera moves) and how
sure the posterior is of it (the top mode's probability). The x axis is the image id of the processed frames.

As the Plots tab's charts, each is created when its first frame arrives (a uPlot created empty kept a blank state
in Chromium), updated in place afterwards, and made again when the objects change (another sequence).
"""

from __future__ import annotations

import html
from dataclasses import dataclass
from typing import Callable

import numpy as np
import viser
import viser.uplot as uplot

from workbench.app import protocol as p
from workbench.app.ui.run.plots import NO_LEGEND, Line, finite_rows, header_html
from workbench.app.ui.widgets.colors import object_color

HEIGHT = 110  # px per chart: four of them under the timeline
FRAME_AXIS: uplot.Axis = {"label": "frame", "labelSize": 16, "size": 34, "incrs": (1, 2, 5, 10, 20, 50, 100, 200)}
AXES: tuple[uplot.Axis, ...] = (FRAME_AXIS, {"size": 52})


@dataclass(frozen=True)
class FrameChart:
    """One chart: ``values(frames)`` -> (F, K), one column per object."""

    key: str
    title: str
    values: Callable[[list[p.SequenceFrame]], np.ndarray]
    y_scale: uplot.Scale


def _coordinate(axis: int):
    return lambda frames: 100.0 * np.stack([f.positions[:, axis] for f in frames])


CHARTS = (
    FrameChart("x", "position x (cm, table frame)", _coordinate(0), {"auto": True}),
    FrameChart("y", "position y (cm, table frame)", _coordinate(1), {"auto": True}),
    FrameChart("z", "height z (cm above the table)", _coordinate(2), {"auto": True}),
    FrameChart("p", "confidence (top mode's probability)", lambda frames: np.stack([f.confidences for f in frames]),
               {"auto": False, "range": (0.0, 1.0)}),
)


def chart_columns(chart: FrameChart, frames: list[p.SequenceFrame]) -> tuple[np.ndarray, ...]:
    """(x: image ids (F',), one (F',) column per object), over the frames where every object has a value."""
    values = chart.values(frames)
    x = np.array([f.im_id for f in frames], dtype=np.float64)
    return finite_rows(x, *values.T)


class FramePlots:
    """The charts across frames, drawn into ``container`` (a folder of the Data tab)."""

    def __init__(self, gui: viser.GuiApi, container: viser.GuiFolderHandle):
        self.gui, self.container = gui, container
        self.lines: tuple[Line, ...] = ()
        self.drawn: dict[str, tuple[viser.GuiHtmlHandle, viser.GuiUplotHandle]] = {}

    def show(self, frames: list[p.SequenceFrame], names: list[str]) -> None:
        """Draw ``frames`` (the processed ones, in order); ``names``: the objects' display names."""
        lines = tuple(Line(html.escape(n), "#%02x%02x%02x" % object_color(k)) for k, n in enumerate(names))
        if lines != self.lines:
            self.clear()
            self.lines = lines
        if not frames or len(frames[0].positions) != len(lines):
            return
        x_range = (float(frames[0].im_id), float(max(frames[-1].im_id, frames[0].im_id + 1)))
        for i, chart in enumerate(CHARTS):
            data = chart_columns(chart, frames)
            if len(data[0]) == 0:
                continue
            scales = {"x": {"time": False, "auto": False, "range": x_range}, "y": chart.y_scale}
            if chart.key in self.drawn:
                plot = self.drawn[chart.key][1]
                plot.data, plot.scales = data, scales
                continue
            with self.container:
                header = self.gui.add_html(header_html(chart.title, lines), order=100.0 + 2 * i)
                plot = self.gui.add_uplot(data, ({"label": "frame"}, *(ln.series() for ln in lines)),
                                          height=HEIGHT, scales=scales, axes=AXES, legend=NO_LEGEND,
                                          order=101.0 + 2 * i)
            self.drawn[chart.key] = (header, plot)

    def clear(self) -> None:
        for header, plot in self.drawn.values():
            header.remove()
            plot.remove()
        self.drawn, self.lines = {}, ()
