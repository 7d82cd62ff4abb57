"""What the user is told beside the run: failures (the error banner, a notification in every tab, the terminal's
log, and the Label or Sessions tab when they concern it), worker restarts, saves, and bugs in drawing (logged, and
kept for the tests)."""

from __future__ import annotations

import logging
from typing import Callable

import viser

from workbench.app import protocol as p
from workbench.app.ui.run.status import RunView
from workbench.app.ui.widgets.markdown import escape
from workbench.errors import InputError

log = logging.getLogger(__name__)


class Reporter:
    """The panel's fixed top: the title (what is loaded), the error banner, and the outlines of refused fields.
    ``state()``: the server's current ``RunView`` (a new one with every frame), which keeps the failures, the
    drawing errors, the worker pids and the restarts."""

    def __init__(self, server: viser.ViserServer, state: Callable[[], RunView]):
        self.server, self.state = server, state
        gui = server.gui
        self.title = gui.add_markdown("**workbench** · nothing loaded")
        self.error = gui.add_markdown("", visible=False)
        self.field_style = gui.add_html("")  # a <style> outlining the fields whose typed value was refused
        # Where a failure about a topic (``Failure.topic``) is also told, beside the button that failed; the tabs
        # that have one add themselves.
        self.topics: dict[str, Callable[[p.Failure], None]] = {}
        # Every current error, banner line by banner line: key (a field's label, or the failure's title and path)
        # -> markdown. All are listed, not only the newest; they go when the input is corrected or an iteration
        # goes through.
        self.current: dict[str, str] = {}
        self.outlined: dict[str, str] = {}  # the refused fields' element ids by label, outlined in red

    def set_title(self, what: str) -> None:
        self.title.content = f"**workbench** · {what}"

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
        """Hide the error banner and the fields' outlines, unless the estimator is gone for good (only a restart
        helps then)."""
        failures = self.state().failures
        last = failures[-1] if failures else None
        if last is not None and last.fatal:
            return
        self.current, self.outlined = {}, {}
        self.outline()
        if self.error.visible:
            self.error.visible = False

    def field_errors(self, errors: dict[str, str], ids: dict[str, str]) -> None:
        """The typed fields of one group (``ids``: their element ids by label) refused now ({label: problem}; they
        are put back to the values in use): each outlined and listed in the banner, with whatever else is wrong,
        the other groups' refusals included. The group's fields not in ``errors`` lose their lines and outlines
        (the banner goes if nothing else is on it). No notification: this runs on every keystroke, and "2.5e" is on
        its way to "2.5e-1" (``refused_put_back`` notifies once the value is put back)."""
        for label in (*ids, *errors):
            self.current.pop(f"field:{label}", None)
            self.outlined.pop(label, None)
        for label, problem in errors.items():
            log.warning("Input error: %s: %s", label, problem)
            self.current[f"field:{label}"] = (f"`{label}`: {escape(problem)} — **kept the value in use**")
            if label in ids:
                self.outlined[label] = ids[label]
        self.outline()
        self.show_banner()

    def refused_put_back(self, refused: dict[str, str]) -> None:
        """The refused fields ({label: problem}) were put back to the values in use: a notification each."""
        for label, problem in refused.items():
            self.notify("Input error", f"{label}: {problem}; the value in use was put back", color="red")

    def outline(self) -> None:
        """Outline in red the fields refused now (``outlined``; none: clear), by their labels' ``for``."""
        css = "".join(
            f'.mantine-Flex-root:has(label[for="{i}"]) input{{outline:2px solid #e03131;outline-offset:-1px}}'
            f'label[for="{i}"]{{color:#e03131;font-weight:600}}' for i in self.outlined.values())
        content = f"<style>{css}</style>" if css else ""
        if self.field_style.content != content:
            self.field_style.content = content

    def show_banner(self) -> None:
        lines = list(self.current.values())
        if not lines:
            self.error.visible = False
            return
        head = f"**⚠ {len(lines)} problems**\n\n" if len(lines) > 1 else ""
        self.error.content = head + "\n".join(f"- {line}" if len(lines) > 1 else f"**⚠** {line}"
                                                     for line in lines)
        self.error.visible = True

    def report(self, failure: p.Failure) -> None:
        # The terminal hears of every failure too: a server started on a bad path must not look healthy there.
        log.warning("%s: %s%s", failure.title, f"{failure.path}: " if failure.path else "", failure.problem)
        if failure.topic in self.topics:
            self.topics[failure.topic](failure)
        state = self.state()
        state.failures.append(failure)
        where = f"`{failure.path}`: " if failure.path else ""
        text = f"**{escape(failure.title)}** — {where}{escape(failure.problem)}"
        self.current[f"{failure.title}|{failure.path}"] = text
        self.show_banner()
        view = state.view  # a failed load leaves the loaded frame in place
        self.set_title(view.title if view else "nothing loaded")
        self.notify(failure.title, f"{failure.path + ': ' if failure.path else ''}{failure.problem}", color="red")

    def engine_died(self, exitcode: int | None, gave_up: bool, reloading: bool) -> None:
        """The estimator process died: restarted (and the frame ``reloading``), or, dying again, given up."""
        if gave_up:
            log.error("the estimator process died again (exit code %s) and was not restarted: restart the server",
                      exitcode)
            self.report(p.Failure("Estimator process keeps dying", f"it exited with code {exitcode} again and was "
                                  "not restarted; see the server's log, then restart the server", fatal=True))
            return
        log.warning("the estimator process died (exit code %s); restarted it%s", exitcode,
                    " and reloading the frame" if reloading else "")
        self.notify("Estimator process restarted", f"The estimator process died (exit code {exitcode}); it was "
                    "restarted" + (" and the frame reloaded: the run starts again." if reloading else "."),
                    color="yellow")

    def notify(self, title: str, body: str, color: str) -> None:
        for client in self.server.get_clients().values():
            client.add_notification(title, body, color=color, auto_close_seconds=15.0)

    def drawing_failed(self, what: str, err: Exception) -> None:
        """Log a bug in drawing ``what`` (a message type or a throttled drawing) and keep it for the tests."""
        log.error("drawing %s", what, exc_info=err)
        self.state().display_errors.append(f"{what}: {err!r}")

    def on_workers(self, msg: p.Workers) -> None:
        """The evaluation workers now (``msg.pids``); a restarted pool is told and counted."""
        state = self.state()
        state.worker_pids = msg.pids
        if msg.restarted:
            state.restarts += 1
            self.notify("Evaluation worker restarted", f"A worker process died ({msg.reason}); a fresh pool took "
                        "over and the iteration was retried. The run goes on.", color="yellow")

    def on_saved(self, msg: p.Saved) -> None:
        # Also where it is seen: the tab's own message can be below the fold of a long panel.
        self.notify(f"Saved {msg.kind}", f"{msg.path}{' · ' + msg.note if msg.note else ''}", color="green")
