"""Step: one iteration. While the engine works on it (up to ~20 s on a real frame) Step is disabled and a spinner
counts the seconds, so that nobody wonders whether the click arrived or sends a second one."""

from __future__ import annotations

import time
from typing import Callable

from workbench.app import protocol as p
from workbench.app.ui.panel import Panel
from workbench.app.ui.ui_thread import UiThread


class StepButton:
    """``running()``: whether a Run is going on (Step stays disabled then); ``before()``: what a Step does first
    (refused settings put back)."""

    def __init__(self, panel: Panel, ui: UiThread, send: Callable[[object], None],
                 running: Callable[[], bool], before: Callable[[], object]):
        self.panel, self.ui, self.send, self.running, self.before = panel, ui, send, running, before
        self.since: float | None = None  # monotonic time the pending Step was sent

    def press(self) -> None:
        """One iteration: Step is disabled and a spinner counts the seconds until the engine answers."""
        self.before()
        if self.since is not None or self.running():
            return
        self.since = started = time.monotonic()
        P = self.panel
        P.step.disabled = True
        P.busy.content = "⏳ **Step running** · 0 s"
        P.busy.visible = P.busy_bar.visible = True
        self.send(p.Step())
        self.ui.later(1.0, lambda: self._count(started))

    def _count(self, started: float) -> None:
        """Another second of the Step sent at ``started``, while it is still out."""
        if self.since != started:
            return
        self.panel.busy.content = f"⏳ **Step running** · {time.monotonic() - started:.0f} s"
        self.ui.later(1.0, lambda: self._count(started))

    def done(self) -> None:
        """The engine answered the Step (or the run started, stopped or failed): Step is back."""
        if self.since is None:
            return
        self.since = None
        P = self.panel
        P.busy.visible = P.busy_bar.visible = False
        P.step.disabled = self.running()
