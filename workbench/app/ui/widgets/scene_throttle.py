"""Redrawing the 3D view at a bounded rate: ``SceneThrottle`` batches the latest drawing of each kind and flushes
them together, at most once per interval, so that the browser draws once for all of them."""

from __future__ import annotations

import time
from typing import Callable

import numpy as np
import viser

from workbench.app.ui.ui_thread import Later, UiThread


class SceneThrottle:
    """Draws into the 3D view at most once per ``interval`` seconds: the latest drawing submitted under each key
    runs at once, or (deferred) by a timer once the interval since the last flush is over and at least ``gather``
    seconds after it was submitted. All of one flush go out as one atomic batch, so the browser draws once for them."""

    def __init__(self, server: viser.ViserServer, ui: UiThread, interval: float, gather: float,
                 on_error: Callable[[str, Exception], None]):
        self.server, self.ui, self.on_error = server, ui, on_error
        self.interval, self.gather = interval, gather
        self.pending: dict[str, Callable[[], None]] = {}  # key -> a function that draws
        self.last = -np.inf  # time.monotonic() of the last flush
        self.timer: Later | None = None

    def submit(self, key: str, draw: Callable[[], None], defer: bool) -> None:
        """Draw with ``draw()`` now, or (``defer``) by the timer: once the interval since the last flush is over,
        and no sooner than ``gather`` seconds from now. A later drawing under the same key replaces this one."""
        self.pending[key] = draw
        if not defer:
            self.flush()
        elif self.timer is None:
            wait = max(self.gather, self.last + self.interval - time.monotonic())
            self.timer = self.ui.later(wait, self.flush)

    def flush(self) -> None:
        """Run every pending drawing now."""
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
        draws, self.pending = self.pending, {}
        if not draws:
            return
        self.last = time.monotonic()
        with self.server.atomic():
            for key, draw in draws.items():
                try:
                    draw()
                except Exception as err:  # a drawing bug must not stop the other drawings
                    self.on_error(key, err)

    def cancel(self) -> None:
        """Drop the pending drawings (a new frame or a reset replaces what they would draw)."""
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
        self.pending = {}
