"""The Inspect tab's controls (``InspectTab``): the settled estimate's confidence and other modes, the particle
chosen by rank, its physics and its heatmap, and how many particles are drawn. ``display.RunDisplay`` builds the tab
and draws what they choose."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import viser

from workbench.app.engine.snapshot import DEFAULT_DISPLAY
from workbench.app.ui.run.modes import NO_POSTERIOR
from workbench.app.ui.run.views import HEATMAP_MODES, SCENE_MODES
from workbench.app.ui.widgets.layout import without_number_box
from workbench.app.ui.widgets.numeric import NumberRule

DRAWN = NumberRule("Particles drawn", 1, 20_000, whole=True)


@dataclass
class InspectTab:
    posterior: viser.GuiMarkdownHandle  # the settled estimate's confidence and other modes, per object
    rank: viser.GuiSliderHandle
    best: viser.GuiButtonHandle
    scene_mode: viser.GuiDropdownHandle
    physics_change: viser.GuiMarkdownHandle
    heatmap_mode: viser.GuiDropdownHandle
    legend: viser.GuiHtmlHandle
    heat_image: viser.GuiImageHandle
    max_particles: viser.GuiTextHandle  # read by DRAWN (``widgets.numeric``)


def build_inspect_tab(gui: viser.GuiApi, particles: int) -> InspectTab:
    """The tab's controls, for a run of ``particles`` (call inside the tab)."""
    posterior = gui.add_markdown(NO_POSTERIOR)
    rank = gui.add_slider("Particle rank", 0, max(1, particles - 1), 1, 0,
                          hint="0 = most likely; or click a particle in the 3D view; the arrow keys step it")
    without_number_box(gui, rank)  # the rank chosen is shown under Physics
    best = gui.add_button("Most likely", icon=viser.Icon.STAR)
    scene_mode = gui.add_dropdown("Physics", SCENE_MODES, initial_value="before + after",
                                  hint="the chosen particle before and after physics projection")
    physics_change = gui.add_markdown("")
    heatmap_mode = gui.add_dropdown("Heatmap", HEATMAP_MODES, initial_value="off",
                                    hint="the chosen particle's fit per pixel, drawn on the observed points")
    legend = gui.add_html("")
    heat_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="chosen particle, problem grid",
                               format="png", visible=False)
    max_particles = gui.add_text(DRAWN.label, DRAWN.show(DEFAULT_DISPLAY),
                                 hint=f"the most likely first; fewer are clearer and cheaper to draw; {DRAWN.span}")
    return InspectTab(posterior=posterior, rank=rank, best=best, scene_mode=scene_mode,
                      physics_change=physics_change, heatmap_mode=heatmap_mode, legend=legend, heat_image=heat_image,
                      max_particles=max_particles)
