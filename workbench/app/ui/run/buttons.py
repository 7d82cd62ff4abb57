"""The run's buttons under the title: Step, Run, Pause, Reset on one row, and the status line above them.

Step is one iteration. While the engine works on it (up to ~20 s on a real frame) Step, Run and Reset are disabled
and a spinner counts the seconds, so that nobody wonders whether the click arrived or sends a second one. A Reset
pressed while an iteration is under way waits for it (the engine takes commands between iterations): it says so,
with the same spinner, until the engine has reset."""

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
        self.since: float | None = None  # monotonic time the pending Step or Reset was sent
        self.what = ""  # what is pending, in words
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
        """One iteration: the buttons wait and a spinner counts the seconds until the engine answers."""
        self.before()
        if self.since is not None or self.running():
            return
        self.wait("Step running")
        self.send(p.Step())

    def press_reset(self, message: p.Reset) -> None:
        """Send the Reset ``message``; while an iteration is under way (a Run, a Step) say that it waits for it."""
        if self.since is not None and self.what.startswith("Reset"):
            return  # one Reset is on its way already
        busy = self.since is not None or self.running()
        self.wait("Reset waits for the iteration under way" if busy else "Resetting")
        self.send(message)

    def wait(self, what: str) -> None:
        """Something was sent (``what``, in words): the buttons wait and a spinner counts the seconds."""
        self.since = started = time.monotonic()
        self.what = what
        self.step.disabled = self.run.disabled = self.reset.disabled = True
        self.busy.content = f"**{what}** · 0 s"
        self.busy.visible = self.busy_bar.visible = True
        self.ui.later(1.0, lambda: self._count(started))

    def _count(self, started: float) -> None:
        """Another second of what was sent at ``started``, while it is still out."""
        if self.since != started:
            return
        self.busy.content = f"**{self.what}** · {time.monotonic() - started:.0f} s"
        self.ui.later(1.0, lambda: self._count(started))

    def done(self) -> None:
        """The engine answered (or the run started, stopped or failed): the buttons are back."""
        if self.since is None:
            return
        self.since, self.what = None, ""
        self.busy.visible = self.busy_bar.visible = False
        running = self.running()
        self.step.disabled = self.run.disabled = running
        self.reset.disabled = False

    def show_running(self, running: bool) -> None:
        """A Run started or stopped: Run and Step wait while it goes, Pause only then."""
        self.run.disabled = running
        self.pause.disabled = not running
        self.step.disabled = running
