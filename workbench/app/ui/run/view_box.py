"""The View box under the run's buttons: the 3D view's camera presets, the visibility bar (one toggle per layer),
the estimate's errors against the ground truth, and the view's one legend. ``display.RunDisplay`` draws what the
toggles choose; ``server.App`` wires the camera presets."""

from __future__ import annotations

import viser

from workbench.app.ui.run.camera import FRAME_OBJECTS, FROM_SENSOR
from workbench.app.ui.widgets.layout import TABLE_CSS

# The visibility bar: one toggle per layer of the 3D view, and what is shown at first.
SHOW_ITEMS = ("points", "particles", "estimate", "modes", "truth", "labels", "heatmap")
SHOWN_BY_DEFAULT = {"points": True, "particles": True, "estimate": True, "modes": True, "truth": True,
                    "labels": True, "heatmap": False}
ON, OFF = "●", "○"


def visibility_options(shown: dict[str, bool]) -> tuple[str, ...]:
    """The bar's buttons: "● points" while shown, "○ points" while hidden."""
    return tuple(f"{ON if shown[k] else OFF} {k}" for k in SHOW_ITEMS)


def visibility_item(option: str) -> str:
    """A clicked button's layer: "● points" -> "points"."""
    return option.split(" ", 1)[-1]


class ViewBox:
    def __init__(self, gui: viser.GuiApi):
        self.shown = dict(SHOWN_BY_DEFAULT)
        with gui.add_folder("View", expand_by_default=True):
            self.camera = gui.add_button_group("Camera", (FRAME_OBJECTS, FROM_SENSOR))
            self.visibility = gui.add_button_group("Show", visibility_options(self.shown))
            gui.add_html(TABLE_CSS)  # for every table of the page, this one first
            self.truth = gui.add_markdown("")  # the estimate against the dataset's ground truth
            with gui.add_folder("Legend", expand_by_default=False):
                self.legend = gui.add_html("")

    def show(self, item: str) -> bool:
        return self.shown[item]

    def set_shown(self, item: str, on: bool) -> None:
        """Record a layer's visibility and relabel its toggle (the caller draws the change)."""
        self.shown[item] = bool(on)
        options = visibility_options(self.shown)
        if tuple(self.visibility.options) != options:
            self.visibility.options = options
