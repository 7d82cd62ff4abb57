"""The Sessions tab: save the whole run (particles, RNG, history, settings, labels) under a name, list the saved
sessions, and continue one.

Listing reads only the sessions' JSON files (cheap) and happens here; saving and loading need the estimator and run
in the engine process. A session whose dataset files changed since the save is loaded only after the user confirms
the warnings. A session file that cannot be read shows its problem in the list and, when loaded, in the panel; the
current run is left as it was.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import viser

from workbench.app import protocol as p
from workbench.app.ui.ui_thread import UiThread
from workbench.app.ui.widgets.markdown import escape
from workbench.app.ui.widgets.quiet import Quiet
from workbench.errors import InputError
from workbench.sessions import store as sessions

NO_SESSIONS = "(no sessions)"
MAX_LISTED = 30


@dataclass
class SessionsTab:
    folder: viser.GuiMarkdownHandle
    name: viser.GuiTextHandle
    overwrite: viser.GuiCheckboxHandle
    save: viser.GuiButtonHandle
    choice: viser.GuiDropdownHandle
    refresh: viser.GuiButtonHandle
    load: viser.GuiButtonHandle
    message: viser.GuiMarkdownHandle
    question: viser.GuiMarkdownHandle
    confirm: viser.GuiButtonHandle
    cancel: viser.GuiButtonHandle
    listing: viser.GuiMarkdownHandle


def build_sessions_tab(gui: viser.GuiApi) -> SessionsTab:
    folder = gui.add_markdown("")
    name = gui.add_text("Session name", "", hint="letters, digits, '.', '_' or '-'")
    overwrite = gui.add_checkbox("Replace a session of that name", False)
    save = gui.add_button("Save session", icon=viser.Icon.DEVICE_FLOPPY)
    choice = gui.add_dropdown("Saved session", (NO_SESSIONS,))
    refresh = gui.add_button("Refresh list", icon=viser.Icon.REFRESH, color="gray")
    load = gui.add_button("Load session", icon=viser.Icon.FOLDER_OPEN,
                          hint="continue the saved run exactly where it stopped (replaces the current run)")
    message = gui.add_markdown("")
    question = gui.add_markdown("", visible=False)
    confirm = gui.add_button("Load anyway", icon=viser.Icon.ALERT_TRIANGLE, color="yellow", visible=False)
    cancel = gui.add_button("Cancel", color="gray", visible=False)
    listing = gui.add_markdown("")
    return SessionsTab(folder=folder, name=name, overwrite=overwrite, save=save, choice=choice, refresh=refresh,
                       load=load, message=message, question=question, confirm=confirm, cancel=cancel, listing=listing)


def listing_markdown(rows: list[sessions.SessionInfo]) -> str:
    if not rows:
        return "No saved sessions in this folder yet."
    lines = []
    for s in rows[:MAX_LISTED]:
        if s.problem is not None:
            lines.append(f"- **{s.name}** — ⚠ cannot be loaded: {s.problem}")
        else:
            lines.append(f"- **{s.name}** — {Path(s.dataset).name} scene {s.scene_id} frame {s.im_id} · iteration "
                         f"{s.iteration} · {s.particles} particles · {s.method} · {s.labelled} labelled · "
                         f"{s.saved_at}")
    more = f"\n\n… and {len(rows) - MAX_LISTED} more" if len(rows) > MAX_LISTED else ""
    return "\n".join(lines) + more


@dataclass
class Sessions:
    """The Sessions tab (``container``): its controls (``tab``), listing ``directory``; ``send`` reaches the engine."""

    gui: viser.GuiApi
    container: viser.GuiTabHandle
    directory: Path
    send: Callable[[object], None]
    ui: UiThread
    quiet: Quiet
    tab: SessionsTab = field(init=False)
    rows: dict[str, sessions.SessionInfo] = field(default_factory=dict)
    pending: Path | None = None  # the session waiting for the user's confirmation
    iteration: Callable[[], int] = lambda: -1  # the current run's iteration (-1: nothing run)
    saved_iteration: int | None = None  # the run's iteration last saved to or loaded from a session
    unsaved_ok: bool = False  # the pending question is about the unsaved run, not a changed dataset

    def __post_init__(self) -> None:
        self.directory = Path(self.directory).expanduser().resolve()
        with self.container:
            self.tab = t = build_sessions_tab(self.gui)
        t.folder.content = f"Folder: `{self.directory}`"
        for button, action in ((t.save, self.save), (t.refresh, self.refresh), (t.load, self.load),
                               (t.confirm, self.confirm), (t.cancel, self.cancel)):
            button.on_click(self.ui.callback(lambda _, action=action: self._guard(action)))
        self.refresh()

    def _guard(self, action: Callable[[], None]) -> None:
        if not self.quiet.active:
            action()

    def refresh(self, select: str | None = None) -> None:
        """Re-read the folder; keep the selection (or choose ``select``)."""
        rows = sessions.list_sessions(self.directory)
        self.rows = {s.name: s for s in rows}
        current = self.tab.choice.value
        options = tuple(self.rows) or (NO_SESSIONS,)
        with self.quiet:
            self.tab.choice.options = options
            self.tab.choice.value = select if select in self.rows else current if current in self.rows else options[0]
            self.tab.listing.content = listing_markdown(rows)

    def save(self) -> None:
        text = self.tab.name.value.strip()
        try:
            name = sessions.check_name(text)
        except InputError as err:
            # Names are refused, never changed silently: offer a valid one in the field for the next click.
            suggestion = sessions.suggest_name(text)
            with self.quiet:
                self.tab.name.value = suggestion
            self.tab.message.content = (f"**⚠ {escape(err.problem)}.** The field now holds `{suggestion}`: press "
                                        "**Save session** again to use it.")
            return
        self.tab.message.content = f"Saving `{name}` …"
        self.send(p.SaveSession(self.directory, name, overwrite=bool(self.tab.overwrite.value)))

    def unsaved(self) -> str | None:
        """What of the current run no session holds ("iteration 7; last saved at iteration 5"), or None (nothing
        run, or saved as it is): asked before a load replaces it."""
        it = self.iteration()
        if it < 0 or it == self.saved_iteration:
            return None
        return f"iteration {it}" + (f"; last saved at iteration {self.saved_iteration}"
                                    if self.saved_iteration is not None else "")

    def load(self) -> None:
        info = self.rows.get(self.tab.choice.value)
        if info is None:
            self.tab.message.content = "No session chosen: save one first, or press **Refresh list**."
            return
        self.ask(None)
        lost = self.unsaved()
        if lost is not None:  # a load replaces the run: ask first
            self.ask(p.SessionQuestion(info.path, []), unsaved=lost)
            return
        self.tab.message.content = f"Loading `{info.name}` …"
        self.send(p.LoadSession(info.path, confirmed=False))

    def load_path(self, path: Path) -> None:
        """Load a session file named on the command line (it may lie outside the listed folder)."""
        self.tab.message.content = f"Loading `{path}` …"
        self.send(p.LoadSession(Path(path), confirmed=False))

    def confirm(self) -> None:
        if self.pending is not None and self.unsaved_ok:
            path = self.pending
            self.ask(None)  # the run may go; the dataset's check still comes
            self.tab.message.content = f"Loading `{path.name}` …"
            self.send(p.LoadSession(path, confirmed=False))
        elif self.pending is not None:
            path, self.pending = self.pending, None
            self.ask(None)
            self.tab.message.content = f"Loading `{path.name}` despite the changes …"
            self.send(p.LoadSession(path, confirmed=True))

    def cancel(self) -> None:
        self.ask(None)
        self.tab.message.content = "Not loaded: the current run goes on."

    def ask(self, question: p.SessionQuestion | None, unsaved: str | None = None) -> None:
        """Show (or, with None, hide) the dataset warnings, or (``unsaved``) that the current run is not saved,
        with their Load anyway / Cancel buttons."""
        t = self.tab
        self.pending = None if question is None else Path(question.path)
        self.unsaved_ok = unsaved is not None
        if unsaved is not None:
            t.question.content = (f"**⚠ The current run is not saved** ({unsaved}): loading `{self.pending.name}` "
                                  "replaces it. Save it first, or load anyway.")
        elif question is not None:
            items = "\n".join(f"- {w}" for w in question.warnings)
            t.question.content = (f"**⚠ The dataset of `{self.pending.name}` changed since it was saved:**\n\n{items}"
                                  "\n\nLoading it anyway continues on the files as they are now; the run will not "
                                  "reproduce the saved one.")
        t.question.visible = t.confirm.visible = t.cancel.visible = question is not None

    # -- engine messages (on the UI thread)

    def on_frame(self, title: str) -> None:
        """A frame was loaded (its run not saved yet): offer a name made from it, unless the user typed one."""
        self.saved_iteration = None
        if not self.tab.name.value.strip():
            with self.quiet:
                self.tab.name.value = sessions.suggest_name(title.replace(" · ", "-"))

    def on_question(self, msg: p.SessionQuestion) -> None:
        self.tab.message.content = ""
        self.ask(msg)

    def on_saved(self, msg: p.Saved) -> None:
        name = Path(msg.path).name.removesuffix(".json")
        self.saved_iteration = self.iteration()
        self.tab.message.content = f"Saved session `{name}` ({msg.note}) to `{msg.path}`"
        with self.quiet:
            self.tab.overwrite.value = False  # replacing is a choice for one save
        self.refresh(select=name)

    def on_restored(self, msg: p.SessionRestored) -> None:
        it = self.saved_iteration = msg.reports[-1]["iteration"] if msg.reports else -1
        text = f"Loaded session `{msg.name}` at iteration {it}; press **Step** or **Run** to continue it."
        if msg.warnings:
            text += " Loaded despite: " + "; ".join(msg.warnings)
        self.tab.message.content = text
        with self.quiet:
            self.tab.name.value = msg.name  # saving again offers to replace what was loaded
        if Path(msg.path).parent.resolve() == self.directory:
            self.refresh(select=msg.name)

    def on_failure(self, failure: p.Failure) -> None:
        where = f"`{failure.path}`: " if failure.path else ""
        self.tab.message.content = f"**⚠ {where}{escape(failure.problem)}**"
