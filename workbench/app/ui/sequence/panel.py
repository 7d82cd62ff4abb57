"""The Data tab's Sequence folder, shown when the loaded frame's scene has several frames: *Next frame*, the
timeline of the processed frames (a click shows one again, as it was left), each with its status, and the plots
across frames (``sequence_plots``). The engine does the work (``engine_sequence``); this only sends the commands
and shows its ``protocol.SequenceState``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import viser

from workbench.app import protocol as p
from workbench.app.ui.sequence.plots import FramePlots
from workbench.app.ui.ui_thread import UiThread
from workbench.app.ui.widgets.markdown import escape


@dataclass
class SequenceTab:
    folder: viser.GuiFolderHandle
    summary: viser.GuiMarkdownHandle
    next: viser.GuiButtonHandle
    timeline: viser.GuiButtonGroupHandle  # one button per processed frame, by image id
    table: viser.GuiMarkdownHandle  # the processed frames with their statuses
    message: viser.GuiMarkdownHandle  # what is going on, or what failed
    plots: FramePlots


def build_sequence_tab(gui: viser.GuiApi, order: float | None = None) -> SequenceTab:
    """The folder, hidden until a sequence is loaded (call inside the Data tab; ``order``: its place there)."""
    folder = gui.add_folder("Sequence", order=order, visible=False)
    with folder:
        summary = gui.add_markdown("")
        nxt = gui.add_button("Next frame", icon=viser.Icon.PLAYER_SKIP_FORWARD,
                             hint="track the scene's next frame from the run on show, as `workbench track` does")
        timeline = gui.add_button_group("Frames", ("–",), hint="show a processed frame again, as it was left")
        table = gui.add_markdown("")
        message = gui.add_markdown("")
    return SequenceTab(folder, summary, nxt, timeline, table, message, FramePlots(gui, folder))


def summary_markdown(msg: p.SequenceState) -> str:
    """What the sequence is and where it stands, in two short sentences."""
    ids = msg.frame_ids
    where = (f"Scene {msg.scene_id}, frames {ids[0]}–{ids[-1]}: frame **{msg.current}** on show, "
             f"{len(msg.frames)} processed.")
    if msg.next_id is None:
        return f"{where} It is the scene's last frame."
    return f"{where} **Next frame** goes to frame {msg.next_id} from this run."


def timeline_markdown(msg: p.SequenceState) -> str:
    """The processed frames, one row each: on show, image id, status, seconds, the camera motion's source."""
    rows = []
    for f in msg.frames:
        status = escape(f.status) + ("" if f.held else " · run not in the session")
        seconds = f"{f.seconds:.1f}" if f.seconds > 0 else "–"
        rows.append(f"| {'▶' if f.im_id == msg.current else ''} | {f.im_id} | {status} | {seconds} | "
                    f"{f.motion or '–'} |")
    return "| | frame | status | s | camera |\n|:---:|:---:|---|---:|:---:|\n" + "\n".join(rows)


class SequencePanel:
    """The Sequence folder (``tab``), built where this is made (at ``order`` there): ``send`` commands to the
    engine; ``show_history(reports, config)``: the run of a frame put on show, for the plots over iterations and
    the status line; ``names()``: the objects' display names. Failures about the sequence: ``on_failure``."""

    def __init__(self, gui: viser.GuiApi, order: float | None, ui: UiThread, send: Callable[[object], None],
                 show_history: Callable[[list[dict], object], None], names: Callable[[], list[str]]):
        self.tab = tab = build_sequence_tab(gui, order)
        self.send, self.show_history, self.names = send, show_history, names
        self.state: p.SequenceState | None = None
        self.waiting = False  # a Next or a jump is with the engine
        tab.next.on_click(ui.callback(lambda _: self.next()))
        tab.timeline.on_click(ui.callback(lambda event: self.jump(event.target.value)))

    def next(self) -> None:
        if self.waiting or self.state is None or self.state.next_id is None:
            return
        self.wait(f"**Going to frame {self.state.next_id}** …")
        self.send(p.NextFrame())

    def jump(self, option: str) -> None:
        if self.waiting or self.state is None or not option.isdigit() or int(option) == self.state.current:
            return
        self.wait(f"**Showing frame {option}** …")
        self.send(p.ShowFrame(int(option)))

    def wait(self, text: str) -> None:
        self.waiting = True
        self.tab.next.disabled = True
        self.tab.message.content = text

    # -- engine messages (on the UI thread)

    def show(self, msg: p.SequenceState) -> None:
        t = self.tab
        self.state, self.waiting = msg, False
        t.folder.visible = msg.scene_id is not None
        if msg.scene_id is None:
            t.plots.clear()
            return
        options = tuple(str(f.im_id) for f in msg.frames)
        if tuple(t.timeline.options) != options:
            t.timeline.options = options
        t.summary.content = summary_markdown(msg)
        t.table.content = timeline_markdown(msg)
        t.next.disabled = msg.next_id is None
        shown = next(f for f in msg.frames if f.im_id == msg.current)
        t.message.content = "" if msg.reports is None else (
            f"Frame {shown.im_id}: {escape(shown.status)}" + (f" in {shown.seconds:.1f} s" if shown.seconds else "")
            + (f", camera motion {shown.motion}" if shown.motion else "") + ".")
        if msg.reports is not None:
            self.show_history(msg.reports, msg.run_config)
        t.plots.show(msg.frames, self.names())

    def on_failure(self, failure: p.Failure) -> None:
        self.waiting = False
        self.tab.next.disabled = self.state is None or self.state.next_id is None
        where = f"`{failure.path}`: " if failure.path else ""
        self.tab.message.content = f"**⚠ {where}{escape(failure.problem)}**"
