"""The run's buttons under the title: Step, Run, Pause, Reset on one row, and the status line above them.

Step is one iteration. While the engine works on it (up to ~20 s on a real frame) Step is disabled and a spinner
counts the seconds, so that nobody wonders whether the click arrived or sends a second one."""

from __future__ import annotations

import time
from typing import Callable

import viser

from workbench.app import protocol as p
from workbench.app.ui.ui_thread import UiThread
from workbench.app.ui.widgets.layout import button_row_css


class RunButtons:
    """``running()``: whether a Run is going on (Step stays disabled then); ``before()``: what a Step does first
    (refused settings put back); ``on_run``, ``on_pause``, ``on_reset``: the other buttons' actions."""

    def __init__(self, gui: viser.GuiApi, ui: UiThread, send: Callable[[object], None], running: Callable[[], bool],
                 before: Callable[[], object], on_run: Callable[[], None], on_pause: Callable[[], None],
                 on_reset: Callable[[], None]):
        self.ui, self.send, self.running, self.before = ui, send, running, before
        self.since: float | None = None  # monotonic time the pending Step was sent
        self.status = gui.add_markdown("No iterations yet.")
        self.busy = gui.add_markdown("", visible=False)  # "Step running · 3 s" while a Step is out
        self.busy_bar = gui.add_progress_bar(100.0, animated=True, visible=False)  # its spinner
        self.step = gui.add_button("Step", icon=viser.Icon.PLAYER_TRACK_NEXT, hint="one iteration")
        self.run = gui.add_button("Run", icon=viser.Icon.PLAYER_PLAY, color="green",
                                  hint="iterate until the budget, convergence or Pause")
        self.pause = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE, disabled=True,
                                    hint="stop after this iteration")
        self.reset = gui.add_button("Reset", icon=viser.Icon.REFRESH, color="gray",
                                    hint="new random particles (seed and likelihood model apply here)")
        # One row: the panel's fixed top stays short.
        gui.add_html(button_row_css([b._impl.uuid for b in (self.step, self.run, self.pause, self.reset)]))
        self.step.on_click(ui.callback(lambda _: self.press()))
        self.run.on_click(ui.callback(lambda _: on_run()))
        self.pause.on_click(ui.callback(lambda _: on_pause()))
        self.reset.on_click(ui.callback(lambda _: on_reset()))

    def press(self) -> None:
        """One iteration: Step is disabled and a spinner counts the seconds until the engine answers."""
        self.before()
        if self.since is not None or self.running():
            return
        self.since = started = time.monotonic()
        self.step.disabled = True
        self.busy.content = "**Step running** · 0 s"
        self.busy.visible = self.busy_bar.visible = True
        self.send(p.Step())
        self.ui.later(1.0, lambda: self._count(started))

    def _count(self, started: float) -> None:
        """Another second of the Step sent at ``started``, while it is still out."""
        if self.since != started:
            return
        self.busy.content = f"**Step running** · {time.monotonic() - started:.0f} s"
        self.ui.later(1.0, lambda: self._count(started))

    def done(self) -> None:
        """The engine answered the Step (or the run started, stopped or failed): Step is back."""
        if self.since is None:
            return
        self.since = None
        self.busy.visible = self.busy_bar.visible = False
        self.step.disabled = self.running()

    def show_running(self, running: bool) -> None:
        """A Run started or stopped: Run and Step wait while it goes, Pause only then."""
        self.run.disabled = running
        self.pause.disabled = not running
        self.step.disabled = running
