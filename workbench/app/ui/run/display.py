"""The run as drawn: the observation, the particle cloud, the chosen particle and its heatmap, the estimate's other
modes (the posterior) in the 3D view, and the Inspect tab's text, legends and images beside them.

While the estimator runs, the 3D view is redrawn at most once per ``SCENE_INTERVAL_S`` (``SceneThrottle``); the
panel's text and plots follow every iteration (``server.App``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np
import viser

from workbench.app import protocol as p
from workbench.app.engine.snapshot import default_drawn
from workbench.app.ui.labelling.labelling import Labelling
from workbench.app.ui.reporting import Reporter
from workbench.app.ui.run.ghosts import ModesLayer
from workbench.app.ui.run.inspect import DRAWN, build_inspect_tab
from workbench.app.ui.run.modes import confidences, posterior_markdown
from workbench.app.ui.run.status import physics_markdown
from workbench.app.ui.run.view_box import ViewBox
from workbench.app.ui.run.views import ChosenLayer, HeatmapLayer, ObservationLayer, ParticleLayer, light_cheaply
from workbench.app.ui.ui_thread import UiThread
from workbench.app.ui.widgets.colors import view_legend_html
from workbench.app.ui.widgets.numeric import NumberField
from workbench.app.ui.widgets.quiet import Quiet
from workbench.app.ui.widgets.scene_throttle import SceneThrottle
from workbench.inference.answer.posterior import Posterior

# While the estimator runs, the 3D view is redrawn at most once per this many seconds. Every batch of scene messages
# makes viser's client draw frames for 250 ms, and a software-rendered frame costs ~0.2 s of CPU, so each redraw
# costs ~0.5 s of CPU: a redraw per iteration (and Chosen apart from Snapshot) kept Chromium busy. The panel's text
# and plots still follow every iteration.
SCENE_INTERVAL_S = 1.0
SCENE_GATHER_S = 0.1  # a deferred redraw waits this long at least, for the rest of its iteration (Chosen)


class RunDisplay:
    """Draws what the engine sends into the 3D view, the Inspect tab ``container`` (built here, ``inspect``) and the
    View box's legend, with the layers ``view_box`` shows. ``send`` reaches the engine (which particle is chosen,
    how many are drawn); ``on_error(what, err)``: a throttled drawing failed."""

    def __init__(self, server: viser.ViserServer, container: viser.GuiTabHandle, ui: UiThread, quiet: Quiet,
                 reporter: Reporter, view_box: ViewBox, labelling: Labelling, particles: int,
                 send: Callable[[object], None]):
        self.server, self.view_box, self.labelling, self.send = server, view_box, labelling, send
        self.drawn_by_user = False  # whether the user has set Particles drawn (else each frame gets its share)
        with container:
            self.inspect = ins = build_inspect_tab(server.gui, particles)
        ins.rank.on_update(ui.callback(lambda _: send(p.Select(int(ins.rank.value)))))
        ins.best.on_click(ui.callback(lambda _: self.pick(0)))
        self.drawn = NumberField(ins.max_particles, DRAWN, ui, quiet, reporter, self.drawn_changed)
        ins.scene_mode.on_update(ui.callback(lambda _: self.redraw_chosen()))
        ins.heatmap_mode.on_update(ui.callback(lambda _: self.heatmap_mode_changed()))
        self.throttle = SceneThrottle(server, ui, SCENE_INTERVAL_S, SCENE_GATHER_S, reporter.drawing_failed)
        light_cheaply(server)
        self.observation = ObservationLayer(server)
        self.particles = ParticleLayer(server, on_pick=lambda rank: ui.call(self.pick, rank))
        self.chosen = ChosenLayer(server)
        self.heatmap = HeatmapLayer(server)
        self.modes = ModesLayer(server)
        self.view: p.ObservationView | None = None  # the frame drawn
        self.posterior: Posterior | None = None  # the settled estimate's, shown (None: none for this estimate)
        self.names: list[str] = []  # the loaded objects' display names, as every part of the panel shows them
        self.choice: p.Chosen | None = None  # the chosen particle drawn
        self.last_heat_mode = "log-likelihood"  # what the visibility bar's heatmap toggle turns on

    def pick(self, rank: int) -> None:
        """Choose the particle at ``rank``: moving the shared slider sends the Select (and shows every tab)."""
        slider = self.inspect.rank
        rank = int(np.clip(rank, 0, slider.max))
        if slider.value == rank:
            self.send(p.Select(rank))
        else:
            slider.value = rank

    def drawn_changed(self, drawn: int, event) -> None:
        """Particles drawn: the engine sends that many; once the user sets it (a client's event), frames keep it."""
        self.drawn_by_user |= event.client is not None
        self.send(p.SetDisplay(drawn))

    def truth_reloaded(self, msg: p.TruthReloaded) -> None:
        """The frame's ground truth read again (a label save or a restore wrote scene_gt.json): drawn anew."""
        if self.view is not None and (msg.gt_T_world_obj is None or len(msg.gt_T_world_obj) == len(self.view.meshes)):
            self.view = replace(self.view, gt_T_world_obj=msg.gt_T_world_obj)
            self.observation.draw(self.view, self.points_visible(), self.view_box.show("truth"))

    def set_frame(self, view: p.ObservationView) -> None:
        """A new frame: its observation, and nothing of a run yet (the caller batches this with ``server.atomic``)."""
        ins = self.inspect
        self.throttle.cancel()
        self.view, self.choice = view, None
        self.observation.draw(view, self.points_visible(), self.view_box.show("truth"))
        self.particles.set_frame(view.meshes)
        self.chosen.set_frame(view)
        self.heatmap.set_frame(view)
        self.modes.set_frame(view.meshes)
        self.posterior = None
        drawn = default_drawn(len(view.meshes))
        if not self.drawn_by_user and drawn != self.drawn.value:  # the frame's share of the outlines drawn
            self.drawn.show(drawn)
            self.send(p.SetDisplay(drawn))
        ins.posterior.content = posterior_markdown(None, [], -1)
        ins.heat_image.visible = False
        ins.legend.content = ""
        ins.physics_change.content = ""
        self.names = [m.name for m in view.meshes]
        self.show_view_legend()

    def show_view_legend(self) -> None:
        view = self.view
        if view is None:
            return
        heat = self.heat_on()
        note = "observed points replaced by a heatmap: its colours are explained beside it" if heat else ""
        content = view_legend_html(self.names, view.color_legend, note, confidences(self.posterior, len(self.names)))
        if self.view_box.legend.content != content:
            self.view_box.legend.content = content

    def show_cloud(self, cloud: p.ParticleCloud, posterior: Posterior | None, defer: bool) -> None:
        """Draw ``cloud`` and the estimate (the settled one where the snapshot has a ``posterior``): now, or
        (``defer``: while running) with the next throttled redraw."""
        self.throttle.submit("particles", lambda: self.draw_particles(cloud, posterior), defer=defer)

    def draw_particles(self, cloud: p.ParticleCloud, posterior: Posterior | None = None) -> None:
        """The particle cloud and the estimate (which an unlabelled selected object's gizmo follows): the run's
        answer where it was settled (each object's top mode: settling may have turned an object over), else the
        most likely particle."""
        estimate = None if posterior is None else np.stack([o.modes[0].T for o in posterior.objects])
        self.particles.update(cloud, estimate)
        if len(cloud.poses):
            self.labelling.editor.show_estimate(cloud.poses[0] if estimate is None else estimate)

    def show_posterior(self, posterior: Posterior | None, iteration: int, defer: bool) -> None:
        """The settled estimate's ``posterior`` of the snapshot of ``iteration`` (None: none for its estimate): its
        other modes as ghosts (now, or with the next throttled redraw), the confidences in the legend and the
        Inspect tab, the modes to label with in the Label tab."""
        if posterior is None and self.posterior is None:
            return  # most snapshots: nothing to show, nothing shown
        self.posterior = posterior
        self.inspect.posterior.content = posterior_markdown(posterior, self.names, iteration)
        self.show_view_legend()
        self.labelling.modes.show(posterior, iteration)
        self.throttle.submit("modes", lambda: self.modes.update(posterior), defer=defer)

    def show_chosen(self, chosen: p.Chosen, defer: bool) -> None:
        """Draw ``chosen``: now, or (``defer``: while running) with the next throttled redraw."""
        self.choice = chosen
        self.throttle.submit("chosen", self.redraw_chosen, defer=defer)

    def redraw_chosen(self) -> None:
        c, ins = self.choice, self.inspect
        if c is None:  # nothing chosen in this run (yet): nothing of an earlier one stays drawn
            self.chosen.clear()
            self.heatmap.nodes.clear()
            ins.legend.content, ins.heat_image.visible, ins.physics_change.content = "", False, ""
            return
        self.chosen.update(c, ins.scene_mode.value)
        legend, image = self.heatmap.update(c, ins.heatmap_mode.value)
        ins.legend.content = legend
        if image is not None:
            ins.heat_image.image = image
        ins.heat_image.visible = image is not None
        ins.physics_change.content = physics_markdown(c, self.names) if c is not None else ""

    def heat_on(self) -> bool:
        return self.inspect.heatmap_mode.value != "off" or self.labelling.tab.heatmap.value != "off"

    def points_visible(self) -> bool:
        """The observed points show when the user wants them and no heatmap is drawn on them."""
        return self.view_box.show("points") and not self.heat_on()

    def apply_visibility(self) -> None:
        """Draw the visibility bar's choices (and the heatmap's) into the 3D view."""
        V = self.view_box
        V.set_shown("heatmap", self.heat_on())
        with self.server.atomic():
            self.observation.set_visible(self.points_visible(), V.show("truth"))
            self.particles.set_visible(V.show("particles"), V.show("estimate"))
            self.modes.set_visible(V.show("modes"))
            self.labelling.editor.set_shown(V.show("labels"))
        self.show_view_legend()

    def toggle(self, item: str) -> None:
        """The visibility bar's ``item`` was clicked: show or hide that layer. The heatmap's toggle switches the
        chosen particle's heatmap between off and the mode last used."""
        if item == "heatmap":
            if self.heat_on():
                self.inspect.heatmap_mode.value = "off"
                self.labelling.tab.heatmap.value = "off"
            else:
                self.inspect.heatmap_mode.value = self.last_heat_mode
            return  # the dropdowns' callbacks redraw
        if item in self.view_box.shown:
            self.view_box.set_shown(item, not self.view_box.show(item))
            self.apply_visibility()

    def heatmap_mode_changed(self) -> None:
        # The heatmap is drawn on the observed points: showing both would bury one under the other. So would the
        # label heatmap, on the same points: one heatmap at a time. The points come back as the user left them.
        mode, label_mode = self.inspect.heatmap_mode, self.labelling.tab.heatmap
        if mode.value != "off":
            self.last_heat_mode = mode.value
            if label_mode.value != "off":
                label_mode.value = "off"
        self.apply_visibility()
        self.redraw_chosen()

    def label_heatmap_mode_changed(self) -> None:
        if self.labelling.tab.heatmap.value != "off" and self.inspect.heatmap_mode.value != "off":
            self.inspect.heatmap_mode.value = "off"
        self.apply_visibility()

    def reset(self) -> None:
        """A new run on the same frame: no particles, no chosen one, no tables of the old run (the Inspect tab's;
        the others' are their owners' to clear)."""
        self.throttle.cancel()
        self.particles.set_frame(self.particles.meshes)
        self.choice = None
        self.chosen.clear()
        self.heatmap.nodes.clear()
        self.show_posterior(None, -1, defer=False)
        self.inspect.legend.content = ""
        self.inspect.heat_image.visible = False
        self.inspect.physics_change.content = ""
        self.labelling.reset_run()
