"""The Label tab's scene_gt.json backups: the backups an overwriting save kept, listed newest first with their time,
and one restored only after the user confirms (as the Sessions tab asks before replacing the run). The engine does
the file work (``protocol.ListBackups``, ``RestoreBackup``): the scene_gt.json it replaces is backed up first, and
a damaged backup is a message here naming the file, with nothing written."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import viser

from workbench.app import protocol as p
from workbench.app.ui.ui_thread import UiThread
from workbench.app.ui.widgets.markdown import escape

NOT_LISTED = "(press List backups)"
NO_BACKUPS = "(no backups)"


@dataclass
class BackupsTab:
    list: viser.GuiButtonHandle
    choice: viser.GuiDropdownHandle
    restore: viser.GuiButtonHandle
    question: viser.GuiMarkdownHandle
    confirm: viser.GuiButtonHandle
    cancel: viser.GuiButtonHandle
    message: viser.GuiMarkdownHandle


def build_backups_tab(gui: viser.GuiApi) -> BackupsTab:
    listing = gui.add_button("List backups", icon=viser.Icon.LIST, color="gray",
                             hint="the backups of the frame's scene_gt.json that overwriting saves kept")
    choice = gui.add_dropdown("Backup", (NOT_LISTED,), hint="newest first")
    restore = gui.add_button("Restore backup", icon=viser.Icon.RESTORE, disabled=True,
                             hint="put the chosen backup back as scene_gt.json (asks first; the current one is kept)")
    question = gui.add_markdown("", visible=False)
    confirm = gui.add_button("Confirm restore", icon=viser.Icon.ALERT_TRIANGLE, color="yellow", visible=False)
    cancel = gui.add_button("Cancel restore", color="gray", visible=False)
    message = gui.add_markdown("")
    return BackupsTab(list=listing, choice=choice, restore=restore, question=question, confirm=confirm,
                      cancel=cancel, message=message)


@dataclass
class Backups:
    """The backups' controls (``tab``, built in the current GUI container). ``send`` reaches the engine."""

    gui: viser.GuiApi
    send: Callable[[object], None]
    ui: UiThread
    tab: BackupsTab = field(init=False)
    names: dict[str, str] = field(default_factory=dict)  # the dropdown's option -> the backup's file name
    pending: str | None = None  # the backup waiting for the user's confirmation
    asked: bool = False  # a list or restore was sent: a labels failure is shown here too

    def __post_init__(self) -> None:
        self.tab = build_backups_tab(self.gui)
        t, on_ui = self.tab, self.ui.callback
        for button, action in ((t.list, self.list), (t.restore, self.ask), (t.confirm, self.confirm),
                               (t.cancel, self.cancel)):
            button.on_click(on_ui(lambda _, action=action: action()))

    def set_frame(self) -> None:
        """Another frame (perhaps another scene): its backups are listed on request."""
        self.cancel()
        self.show(p.Backups("", []), listed=False)
        self.tab.message.content = ""

    def list(self) -> None:
        self.cancel()
        self.asked = True
        self.tab.message.content = "Listing …"
        self.send(p.ListBackups())

    def ask(self) -> None:
        name = self.names.get(self.tab.choice.value)
        if name is None:
            self.tab.message.content = "**⚠ List the backups first, then choose one.**"
            return
        self.pending = name
        when = self.tab.choice.value.split(" · ")[0]
        self.tab.question.content = (f"**Restore `{name}`** (made {when}) as the scene's scene_gt.json? The current "
                                     "scene_gt.json is backed up first.")
        self.show_question(True)

    def confirm(self) -> None:
        if self.pending is None:
            return
        name, self.pending = self.pending, None
        self.show_question(False)
        self.asked = True
        self.tab.message.content = f"Restoring `{name}` …"
        self.send(p.RestoreBackup(name))

    def cancel(self) -> None:
        self.pending = None
        self.show_question(False)

    def show_question(self, shown: bool) -> None:
        t = self.tab
        t.question.visible = t.confirm.visible = t.cancel.visible = shown
        t.restore.disabled = shown or not self.names

    # -- engine messages

    def show(self, msg: p.Backups, listed: bool = True) -> None:
        """The scene's backups, newest first (the newest chosen)."""
        self.names = {f"{when} · {name}": name for name, when in msg.backups}
        options = tuple(self.names) or ((NO_BACKUPS,) if listed else (NOT_LISTED,))
        self.tab.choice.options = options
        self.tab.choice.value = options[0]
        self.tab.restore.disabled = not self.names or self.pending is not None
        if listed and self.asked:
            self.asked = False
            self.tab.message.content = (f"{len(self.names)} backup(s) of `{msg.path}`" if self.names else
                                        f"No backups of `{msg.path}` yet: an overwriting save keeps one")

    def show_restored(self, msg: p.Saved) -> None:
        self.asked = False
        self.tab.message.content = f"Restored `{msg.path}` · {msg.note}"

    def show_failure(self, failure: p.Failure) -> None:
        if self.asked:
            self.asked = False
            where = f"`{failure.path}`: " if failure.path else ""
            self.tab.message.content = f"**⚠ {where}{escape(failure.problem)}**"
