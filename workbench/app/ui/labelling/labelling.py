"""Labelling ground truth in the browser: the Label tab. The labels themselves are edited in the 3D view and the
tab's pose fields (``label_editor.LabelEditor``); this module adds the actions and shows what the engine answers.

Everything that computes (snap, fit, the heatmap of the labelled scene, the errors of the estimate, saving) runs
in the engine process: the editor sends ``SetLabels`` on every change and this module shows what comes back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import viser

from workbench.app import protocol as p
from workbench.app.ui.labelling.backups import Backups
from workbench.app.ui.labelling.controls import LabelTab, build_label_tab
from workbench.app.ui.labelling.editor import LabelEditor
from workbench.app.ui.labelling.mode_choice import ModeChoice
from workbench.app.ui.labelling.sequence_labels import SequenceLabelsPanel
from workbench.app.ui.run.views import HeatmapLayer
from workbench.app.ui.ui_thread import UiThread
from workbench.app.ui.widgets.colors import named
from workbench.app.ui.widgets.quiet import Quiet


def errors_markdown(msg: p.LabelErrors, names: list[str]) -> str:
    """The estimate's errors against the labels, one row per object (``names``: the objects' display names)."""
    rows = []
    for k, e in enumerate(msg.errors[:len(names)]):
        name = named(k, names[k])
        if e["position_error_m"] is None:
            rows.append(f"| {name} | — | — | — |")
        else:
            rows.append(f"| {name} | {e['position_error_m'] * 100:.2f} | {e['rotation_error_deg']:.1f} | "
                        f"{e['add_s_m'] * 1000:.1f} |")
    if all(e["position_error_m"] is None for e in msg.errors):
        return ""
    return (f"**Best estimate vs label** (iteration {msg.iteration})\n\n"
            "| object | position (cm) | rotation (°) | ADD-S (mm) |\n|---|---:|---:|---:|\n" + "\n".join(rows) +
            "\n\n<small>rotation up to the object's symmetries; — not labelled</small>")


@dataclass
class Labelling:
    """The Label tab (``container``): its controls (``tab``), its editor (``editor``, the labels and their gizmos),
    its actions, and the label heatmap. ``send`` reaches the engine; ``on_heatmap_mode`` tells the app that the
    label heatmap was switched (it hides the observed points under it)."""

    server: viser.ViserServer
    container: viser.GuiTabHandle
    send: Callable[[object], None]
    ui: UiThread
    quiet: Quiet
    reporter: object  # shows a refused typed pose value (``Reporter.field_errors``)
    on_heatmap_mode: Callable[[], None] = lambda: None
    tab: LabelTab = field(init=False)
    editor: LabelEditor = field(init=False)
    heatmap: HeatmapLayer = field(init=False)
    modes: ModeChoice = field(init=False)
    backups: Backups = field(init=False)
    sequence: SequenceLabelsPanel = field(init=False)  # the whole sequence's labels, shown with a sequence

    def __post_init__(self) -> None:
        with self.container:
            self.tab = build_label_tab(self.server.gui)
            with self.tab.backups:
                self.backups = Backups(self.server.gui, self.send, self.ui)
            # Above the backups: next to the frame's own Save labels, whose labels it starts from.
            self.sequence = SequenceLabelsPanel(self.server.gui, self.ui, self.send, lambda: self.editor.selected(),
                                                lambda: self.editor.names, order=self.tab.backups.order - 0.5)
        self.heatmap = HeatmapLayer(self.server, path="/label_heatmap")
        self.editor = LabelEditor(self.server, self.tab, self.send, self.ui, self.quiet, self.reporter,
                                  on_unlabelled=self.clear_heatmap)
        self.modes = ModeChoice(self.server.gui, self.tab.modes)
        t, on_ui = self.tab, self.ui.callback
        t.use_best.on_click(on_ui(lambda _: self.act(p.UseBestAsLabel(*self.modes.chosen()),
                                                     "Taking the best estimate …")))
        t.snap.on_click(on_ui(lambda _: self.act(p.SnapLabels(), "Snapping …")))
        t.fit.on_click(on_ui(lambda _: self.act(p.FitLabels(), "Fitting …")))
        t.heatmap.on_update(on_ui(lambda _: self.editor.guarded(self.heatmap_mode_changed)))
        t.save.on_click(on_ui(lambda _: self.save()))

    # -- frame, engine messages

    def set_frame(self, view: p.ObservationView) -> None:
        """New frame: nothing labelled until the engine says."""
        self.heatmap.set_frame(view)
        self.editor.set_frame(view)
        self.modes.set_frame(self.editor.names)
        self.backups.set_frame()
        if view.rgb_image is not None:
            self.tab.rgb_image.image = view.rgb_image
        self.tab.rgb_image.visible = view.rgb_image is not None
        with self.quiet:
            self.tab.result.content = ""
            self.tab.errors.content = ""
            self.tab.legend.content = ""

    def reset_run(self) -> None:
        """A new run on the same frame: no errors of the old estimate, and no estimate to follow."""
        self.tab.errors.content = ""
        self.editor.show_estimate(None)

    def show_labels(self, msg: p.Labels) -> None:
        if len(msg.labels) != len(self.editor.labels):
            return
        if msg.note or msg.reason in ("frame", "session"):
            self.tab.result.content = msg.note
        if not any(T is not None for T in msg.labels):
            self.clear_heatmap()
        self.editor.set_labels(msg.labels)

    def show_heatmap(self, msg: p.LabelHeatmap) -> None:
        mode = self.tab.heatmap.value
        if mode == "off" or not any(T is not None for T in self.editor.labels):
            return
        subject = "labelled scene" + (f" (unlabelled: {msg.filled})" if msg.filled else "")
        legend, _ = self.heatmap.draw(msg.pixel_loglik, msg.residual, msg.loglik, mode, subject)
        self.tab.legend.content = legend

    def show_errors(self, msg: p.LabelErrors) -> None:
        if len(msg.errors) == len(self.editor.labels):
            self.tab.errors.content = errors_markdown(msg, self.editor.names)

    def show_saved(self, msg: p.Saved) -> None:
        if msg.kind == "ground truth":  # a backup restored
            self.backups.show_restored(msg)
            return
        note = f" · {msg.note}" if msg.note else ""
        self.tab.saved.content = f"Saved labels to `{msg.path}`{note}"

    def show_failure(self, failure: p.Failure) -> None:
        self.tab.result.content = f"**⚠ {failure.problem}**"
        self.backups.show_failure(failure)

    # -- actions

    def act(self, cmd, doing: str) -> None:
        if self.quiet.active:
            return
        self.tab.result.content = doing
        self.send(cmd)

    def heatmap_mode_changed(self) -> None:
        if self.tab.heatmap.value == "off":
            self.clear_heatmap()
        self.editor.send_labels()  # the engine renders the labelled scene only while the heatmap is on
        self.on_heatmap_mode()

    def clear_heatmap(self) -> None:
        self.heatmap.nodes.clear()
        self.tab.legend.content = ""

    def save(self) -> None:
        if self.quiet.active:
            return
        overwrite = bool(self.tab.overwrite_original.value)
        self.tab.saved.content = "Saving …"
        # Overwriting the dataset's ground truth is a choice made for one save, not a mode that stays on.
        with self.quiet:
            self.tab.overwrite_original.value = False
        self.send(p.SaveLabels(overwrite_original=overwrite))
