"""What the user is told beside the run: failures (the error banner, a notification in every tab, the terminal's
log, and the Label or Sessions tab when they concern it), worker restarts, saves, and bugs in drawing (logged, and
kept for the tests)."""

from __future__ import annotations

import logging
import threading
from typing import Callable

import viser

from workbench.app import protocol as p
from workbench.app.labelling import Labelling
from workbench.app.panel import Panel
from workbench.app.sessions_panel import Sessions
from workbench.app.status import RunView
from workbench.errors import InputError

log = logging.getLogger(__name__)


class Reporter:
    """``state()``: the server's current ``RunView`` (a new one with every frame), which keeps the failures, the
    drawing errors, the worker pids and the restarts."""

    def __init__(self, server: viser.ViserServer, panel: Panel, lock: threading.RLock, state: Callable[[], RunView],
                 labelling: Labelling, sessions: Sessions):
        self.server, self.panel, self.lock, self.state = server, panel, lock, state
        self.labelling, self.sessions = labelling, sessions

    def guarded(self, action: Callable[[], None]) -> None:
        """Run a panel action; bad input becomes a message in the panel, never a dead callback. An action that
        goes through clears the banner of an earlier bad input: the user corrected it."""
        try:
            action()
        except InputError as err:
            self.report(p.Failure("Input error", err.problem, err.path))
        else:
            self.clear_error()

    def clear_error(self) -> None:
        """Hide the error banner, unless the estimator is gone for good (only a restart helps then)."""
        with self.lock:
            failures = self.state().failures
            last = failures[-1] if failures else None
            if self.panel.error.visible and not (last is not None and last.fatal):
                self.panel.error.visible = False

    def report(self, failure: p.Failure) -> None:
        # The terminal hears of every failure too: a server started on a bad path must not look healthy there.
        log.warning("%s: %s%s", failure.title, f"{failure.path}: " if failure.path else "", failure.problem)
        with self.lock:
            if failure.topic == "session":
                self.sessions.on_failure(failure)
            elif failure.topic == "labels":
                self.labelling.show_failure(failure)
            state = self.state()
            state.failures.append(failure)
            where = f"`{failure.path}`: " if failure.path else ""
            self.panel.error.content = f"**⚠ {failure.title}** — {where}{failure.problem}"
            self.panel.error.visible = True
            view = state.view  # a failed load leaves the loaded frame in place
            self.panel.title.content = f"**workbench** · {view.title if view else 'nothing loaded'}"
        self.notify(failure.title, f"{failure.path + ': ' if failure.path else ''}{failure.problem}", color="red")

    def notify(self, title: str, body: str, color: str) -> None:
        for client in self.server.get_clients().values():
            client.add_notification(title, body, color=color, auto_close_seconds=15.0)

    def drawing_failed(self, what: str, err: Exception) -> None:
        """Log a bug in drawing ``what`` (a message type or a throttled drawing) and keep it for the tests."""
        log.error("drawing %s", what, exc_info=err)
        with self.lock:
            self.state().display_errors.append(f"{what}: {err!r}")

    def on_workers(self, msg: p.Workers) -> None:
        state = self.state()
        state.worker_pids = msg.pids
        if msg.restarted:
            state.restarts += 1
            self.notify("Evaluation worker restarted", f"A worker process died ({msg.reason}); a fresh pool took "
                        "over and the iteration was retried. The run goes on.", color="yellow")
        where = f"{len(msg.pids)} worker processes" if msg.pids else "in the estimator process"
        restarts = f" · restarted {state.restarts}×" if state.restarts else ""
        self.panel.workers.content = f"Evaluation: {where}{restarts}"

    def on_saved(self, msg: p.Saved) -> None:
        if msg.kind == "session":
            self.sessions.on_saved(msg)
        else:
            self.labelling.show_saved(msg)
        # Also where it is seen: the tab's own message can be below the fold of a long panel.
        self.notify(f"Saved {msg.kind}", f"{msg.path}{' · ' + msg.note if msg.note else ''}", color="green")
