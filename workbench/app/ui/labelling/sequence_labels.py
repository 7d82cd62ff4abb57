"""The Label tab's *Sequence labels* folder, shown while the loaded frame's scene has several frames: one label per
object for the whole sequence, checked against every frame's depth (``engine.label_sequence`` does the work; this
only sends its commands and shows ``protocol.SequenceLabelState``).

The timeline marks each frame by its worst object: a coloured dot in the table, and a plain symbol on the frame's
button (viser's buttons of a group share one colour; headless Chromium has no emoji font): ✓ every object agrees
on at least ``GOOD`` of its seen pixels, ~ one agrees on less, ✗ the frame is flagged (one agrees on less than the
check's ``min_agree``), · nothing could be checked. A click on a frame shows it; *Next flagged frame* shows the
next flagged one after the frame on show. *Propagate* takes the object chosen in the Label tab's Object list.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import viser

from workbench.app import protocol as p
from workbench.app.ui.ui_thread import UiThread
from workbench.app.ui.widgets.colors import named
from workbench.app.ui.widgets.markdown import escape

GOOD = 0.8  # a frame whose worst object agrees on this share of its seen pixels or more is green
# grade -> (the button's symbol, the table dot's colour)
GRADES = {"good": ("✓", (46, 160, 67)), "fair": ("~", (230, 150, 20)), "flagged": ("✗", (215, 45, 45)),
          "unchecked": ("·", (150, 150, 150))}
STARTS = {"current labels": "current", "saved labels": "saved"}
PROPAGATE = ("to every frame", "from this frame on")


def grade(frame: p.LabelledFrame) -> str:
    """A frame's grade by its worst object: "flagged", "fair", "good" or "unchecked"."""
    if frame.flagged:
        return "flagged"
    if frame.worst is None:
        return "unchecked"
    return "good" if frame.worst >= GOOD else "fair"


def option(frame: p.LabelledFrame) -> str:
    """A frame's button in the timeline: its image id and its grade's symbol."""
    return f"{frame.im_id} {GRADES[grade(frame)][0]}"


def dot(which: str) -> str:
    r, g, b = GRADES[which][1]
    return (f'<span style="display:inline-block;width:0.8em;height:0.8em;border-radius:50%;vertical-align:-0.1em;'
            f'background:rgb({r},{g},{b})" title="{which}"></span>')


def table_markdown(msg: p.SequenceLabelState, current: int, names: list[str]) -> str:
    """One row per labelled frame: on show, a dot of its grade, image id, its worst agreement, and each flagged
    object with its agreement and whether the depth sees past it or something is in front of it."""
    rows = []
    for f in msg.frames:
        worst = "–" if f.worst is None else f"{f.worst:.0%}"
        why = ", ".join(f"{named(k, names[k]) if k < len(names) else c['obj_id']} {c['agree']:.0%} "
                        f"({'seen past' if c['through'] >= c['front'] else 'behind something'})"
                        for k, c in enumerate(f.checks) if c["flagged"])
        rows.append(f"| {'▶' if f.im_id == current else ''} | {dot(grade(f))} | {f.im_id} | {worst} | "
                    f"{why or '–'} |")
    return "| | | frame | worst | flagged |\n|:---:|:---:|:---:|---:|---|\n" + "\n".join(rows)


def summary_markdown(msg: p.SequenceLabelState) -> str:
    flagged = [f.im_id for f in msg.frames if f.flagged]
    ids = [f.im_id for f in msg.frames]
    head = f"Labels of frames {ids[0]}–{ids[-1]}: "
    if not flagged:
        return head + "**no frame is flagged**."
    shown = ", ".join(map(str, flagged[:12])) + (" …" if len(flagged) > 12 else "")
    return head + f"**{len(flagged)} flagged** ({shown})."


@dataclass
class SequenceLabelsTab:
    folder: viser.GuiFolderHandle
    frames: viser.GuiTextHandle  # "A:B", empty for all
    start: viser.GuiDropdownHandle
    check: viser.GuiButtonHandle
    summary: viser.GuiMarkdownHandle
    timeline: viser.GuiButtonGroupHandle  # one button per labelled frame: image id and grade symbol
    next_flagged: viser.GuiButtonHandle
    table: viser.GuiMarkdownHandle
    propagate: viser.GuiButtonGroupHandle
    end: viser.GuiButtonGroupHandle  # per object seen through to the end: end its label on the frame before
    fit: viser.GuiButtonHandle
    overwrite_original: viser.GuiCheckboxHandle
    save: viser.GuiButtonHandle
    message: viser.GuiMarkdownHandle  # what is going on, what the last action did, or what failed


def build_sequence_labels_tab(gui: viser.GuiApi, order: float | None = None) -> SequenceLabelsTab:
    """The folder, hidden until a sequence is loaded (call inside the Label tab; ``order``: its place there)."""
    folder = gui.add_folder("Sequence labels", order=order, expand_by_default=True, visible=False)
    with folder:
        frames = gui.add_text("Label frames", "", hint="A:B, image ids, both included; empty: every frame")
        start = gui.add_dropdown("Start from", tuple(STARTS), hint="this frame's labels (every object labelled), "
                                 "carried to every frame by its camera pose, or the sequence labels saved before")
        check = gui.add_button("Check every frame", icon=viser.Icon.CHECKLIST,
                               hint="each frame's labels against its depth: how much of each object's seen "
                                    "surface the sensor sees within 1 cm")
        summary = gui.add_markdown("")
        timeline = gui.add_button_group("Labelled frames", ("–",), hint="✓ agrees, ~ partly, ✗ flagged, · not "
                                        "checked: show that frame")
        next_flagged = gui.add_button("Next flagged frame", icon=viser.Icon.PLAYER_TRACK_NEXT, color="red")
        table = gui.add_markdown("")
        propagate = gui.add_button_group("Propagate", PROPAGATE, hint="the selected object's label on this frame "
                                         "becomes its pose on every frame, or from this frame on; all re-checked")
        end = gui.add_button_group("End label", ("–",), visible=False,
                                   hint="the depth sees through this object from that frame to the end: taken out")
        fit = gui.add_button("Fit to all frames", icon=viser.Icon.TARGET,
                             hint="the still labels fitted to the depth of a spread of frames at once")
        overwrite = gui.add_checkbox("Overwrite the scene's ground truth", False,
                                     hint="write the scene's own scene_gt.json and scene_gt_info.json (backups "
                                          "kept); otherwise scene_gt_labels.json")
        save = gui.add_button("Save sequence labels", icon=viser.Icon.DEVICE_FLOPPY)
        message = gui.add_markdown("")
    return SequenceLabelsTab(folder, frames, start, check, summary, timeline, next_flagged, table, propagate, end,
                             fit, overwrite, save, message)


class SequenceLabelsPanel:
    """The folder (``tab``, built in the current GUI container at ``order``): ``send`` reaches the engine,
    ``selected()`` is the Label tab's chosen object (its index, or None) and ``names()`` the objects' display
    names."""

    def __init__(self, gui: viser.GuiApi, ui: UiThread, send: Callable[[object], None],
                 selected: Callable[[], int | None], names: Callable[[], list[str]], order: float | None = None):
        self.tab = t = build_sequence_labels_tab(gui, order)
        self.send, self.selected, self.names = send, selected, names
        self.state: p.SequenceLabelState | None = None
        self.current = -1  # the image id on show
        self.doing: str | None = None  # what the command out does, in words (None: none is out)
        self.ends: dict[str, tuple[int, int]] = {}  # the End label button -> (object index, last frame)
        on_ui = ui.callback
        t.check.on_click(on_ui(lambda _: self.act(p.CheckSequenceLabels(STARTS[t.start.value], t.frames.value),
                                                  "**Checking every frame** …")))
        t.timeline.on_click(on_ui(lambda event: self.show_frame(event.target.value)))
        t.next_flagged.on_click(on_ui(lambda _: self.next_flagged()))
        t.propagate.on_click(on_ui(lambda event: self.propagate(event.target.value)))
        t.end.on_click(on_ui(lambda event: self.end(event.target.value)))
        t.fit.on_click(on_ui(lambda _: self.act(p.FitSequenceLabels(), "**Fitting to all frames** … (this takes "
                                                "a while: each frame's depth is rendered for every step)")))
        t.save.on_click(on_ui(lambda _: self.save()))

    # -- actions

    def act(self, cmd, doing: str) -> None:
        """Send ``cmd``, saying what it does (``doing``), unless another is out: the folder's buttons wait until the
        engine is done with it (``done``), so that a click cannot queue behind a fit or a check that takes a while.
        viser cannot disable a button group, so a click on one (a frame, Propagate, End label) says to wait."""
        if self.doing is not None:
            self.tab.message.content = f"{self.doing} · **wait for it to finish**"
            return
        self.tab.message.content = self.doing = doing
        self.wait(True)
        self.send(cmd)

    def wait(self, waiting: bool) -> None:
        t = self.tab
        for button in (t.check, t.next_flagged, t.fit, t.save):
            button.disabled = waiting

    def show_frame(self, value: str) -> None:
        im = value.split(" ")[0]
        if im.isdigit() and int(im) != self.current:
            self.act(p.ShowLabelledFrame(int(im)), f"**Showing frame {im}** …")

    def next_flagged(self) -> None:
        flagged = [f.im_id for f in self.state.frames if f.flagged] if self.state and self.state.scene_id is not None \
            else []
        if not flagged:
            self.tab.message.content = "No frame is flagged." if self.state else "Check every frame first."
            return
        after = [i for i in flagged if i > self.current]
        self.act(p.ShowLabelledFrame((after or flagged)[0]), f"**Showing frame {(after or flagged)[0]}** …")

    def propagate(self, how: str) -> None:
        k = self.selected()
        if k is None:
            self.tab.message.content = "**⚠ Choose the object to propagate in the Object list above.**"
            return
        where = "from this frame on" if how == PROPAGATE[1] else "to every frame"
        self.act(p.PropagateLabel(k, from_here=how == PROPAGATE[1]),
                 f"**Propagating** {escape(self.names()[k])} {where}, checking every frame …")

    def end(self, value: str) -> None:
        if value in self.ends:
            k, last = self.ends[value]
            self.act(p.EndSequenceLabel(k, last), f"**Ending** the label on frame {last} …")

    def save(self) -> None:
        overwrite = bool(self.tab.overwrite_original.value)
        self.tab.overwrite_original.value = False  # a choice for one save, as the frame's Save labels
        self.act(p.SaveSequenceLabels(overwrite_original=overwrite), "Saving …")

    # -- engine messages (on the UI thread)

    def show_sequence(self, msg: p.SequenceState) -> None:
        """The timeline's state: the folder is there while a sequence is loaded; the frame on show is marked."""
        self.tab.folder.visible = msg.scene_id is not None
        self.current = msg.current
        if self.state is not None and self.state.scene_id is not None:
            self.tab.table.content = table_markdown(self.state, self.current, self.names())

    def show(self, msg: p.SequenceLabelState) -> None:
        t = self.tab
        self.state = msg
        if msg.scene_id is None:
            t.summary.content = t.table.content = t.message.content = ""
            t.timeline.options = ("–",)
            t.end.visible = False
            return
        options = tuple(option(f) for f in msg.frames)
        if tuple(t.timeline.options) != options:
            t.timeline.options = options
        t.summary.content = summary_markdown(msg)
        t.table.content = table_markdown(msg, self.current, self.names())
        names = self.names()
        prev = {f.im_id: e.im_id for e, f in zip(msg.frames, msg.frames[1:])}
        self.ends = {f"{names[k] if k < len(names) else obj_id}: last frame {prev[first]}": (k, prev[first])
                     for k, obj_id, first in msg.gone if first in prev}
        if self.ends:
            t.end.options = tuple(self.ends)
        t.end.visible = bool(self.ends)
        t.message.content = msg.note

    def show_progress(self, msg: p.SequenceLabelProgress) -> None:
        self.tab.message.content = f"**{escape(msg.text)}**"

    def show_saved(self, msg: p.Saved) -> None:
        note = f" · {msg.note}" if msg.note else ""
        self.tab.message.content = f"Saved sequence labels to `{msg.path}`{note}"

    def done(self, _: p.SequenceLabelsDone | None = None) -> None:
        """The engine has done with the command out (or restarted and lost it): the buttons are back."""
        self.doing = None
        self.wait(False)

    def on_failure(self, failure: p.Failure) -> None:
        where = f"`{failure.path}`: " if failure.path else ""
        self.tab.message.content = f"**⚠ {where}{escape(failure.problem)}**"
