"""The Label tab's six pose fields (x, y, z in cm; roll, pitch, yaw in degrees) of the selected object, read by
the panel's one rule for numbers (``widgets.numeric``): a refused value is shown in red and put back, and never
reaches the label."""

from __future__ import annotations

from typing import Callable

import numpy as np

from workbench.app.ui.labelling.controls import ANGLE_RULES, POSITION_RULES, LabelTab
from workbench.app.ui.ui_thread import Later, UiThread
from workbench.app.ui.widgets.numeric import REVERT_S, Refusals, resend
from workbench.app.ui.widgets.quiet import Quiet
from workbench.errors import InputError
from workbench.geometry import matrix_to_euler

RULES = (*POSITION_RULES, *ANGLE_RULES)


class PoseFields:
    """``on_typed(i, value)``: field ``i`` (0-2 position in cm, 3-5 angles in degrees, in RULES' order) was typed
    and reads as ``value``. ``reporter`` shows refused values (``Reporter.field_errors``)."""

    def __init__(self, tab: LabelTab, ui: UiThread, quiet: Quiet, reporter,
                 on_typed: Callable[[int, float], None]):
        self.handles = (*tab.position, *tab.angles)
        self.ui, self.quiet, self.on_typed = ui, quiet, on_typed
        # Fields the server wrote since the browser last sent them, and the resends due once the typing pauses
        # (``typed``).
        self.written: set[int] = set()
        self.resyncs: dict[int, Later] = {}
        # The pose shown, to the last bit: the fields show it rounded, and an angle typed into one field keeps the
        # other two angles as they were, not as rounded.
        self.values = np.zeros(6)
        self.refusals = Refusals(ui, quiet, reporter, self.ids, self.restore)
        for i, h in enumerate(self.handles):
            h.on_update(ui.callback(lambda _, i=i: self.typed(i)))

    def ids(self) -> dict[str, str]:
        return {r.label: h._impl.uuid for r, h in zip(RULES, self.handles)}

    def show(self, T: np.ndarray, confirmed: bool = False) -> None:
        """Show pose ``T`` (4, 4; table frame) in the fields (call inside ``Quiet``). A field that already reads as
        its value keeps its text: rewriting "1." as "1.00" would fight the user typing "1.5"; so does one being
        typed into ("-" on its way to "-3", refused until then: ``Refusals`` puts the value back once the typing
        pauses), though the run's estimate moves an unlabelled object's fields every iteration.

        ``confirmed``: ``T`` is the engine's answer to a change; a field the server already holds at its value is
        sent again. viser sends only changed values, and a value the server wrote (an earlier answer) can reach the
        browser after the user's typing reached the server: the server then holds what was typed while the browser
        shows the older value, which no later equal write would correct."""
        self.values = np.concatenate([T[:3, 3] * 100.0, np.degrees(matrix_to_euler(T[:3, :3]))])
        for i, (rule, h, v) in enumerate(zip(RULES, self.handles, self.values)):
            if rule.label in self.refusals.refused:
                continue
            if not rule.shows(h.value, v):
                h.value = rule.show(v)
                self.written.add(i)
            elif confirmed:
                resend(h)

    def angles_with(self, i: int, value: float) -> np.ndarray:
        """The angles shown (roll, pitch, yaw; degrees), angle field ``i`` (3-5) set to ``value``."""
        angles = self.values[3:].copy()
        angles[i - 3] = value
        return angles

    def typed(self, i: int) -> None:
        """Field ``i`` was typed: every field of the six is read (one refused earlier may still be), the refused
        ones are shown, and field ``i``'s value, if it reads well, goes to ``on_typed``.

        Where the server wrote field ``i`` since the browser last sent it (a new frame's labels, the run's estimate),
        the write and this keystroke may have crossed: the browser then shows the written value while the server
        holds the typed one, and a plain edit gets no answer from the engine to correct it (``show``'s
        ``confirmed``). So the value held is sent again once the typing pauses (REVERT_S after the last keystroke;
        sooner would fight the typing). Otherwise the field goes on showing the other value, and the next edit is typed
        from it."""
        if self.quiet.active:
            return  # the server showing a pose, not the user typing
        pending = self.resyncs.pop(i, None)
        if pending is not None:
            pending.cancel()
        errors, value = {}, None
        for j, (rule, h) in enumerate(zip(RULES, self.handles)):
            try:
                v = rule.parse(h.value)
            except InputError as err:
                errors[rule.label] = err.problem
            else:
                value = v if j == i else value
        self.refusals.refuse(errors)
        if value is not None and (i in self.written or pending is not None):
            self.written.discard(i)
            self.resyncs[i] = self.ui.later(REVERT_S, lambda: self._resync(i))
        if value is not None:
            self.on_typed(i, value)

    def _resync(self, i: int) -> None:
        self.resyncs.pop(i, None)
        resend(self.handles[i])

    def restore(self, labels: tuple[str, ...]) -> None:
        """Put the pose shown back into the fields labelled ``labels`` (``Refusals`` calls this inside ``Quiet``)."""
        for i, (rule, h, v) in enumerate(zip(RULES, self.handles, self.values)):
            if rule.label in labels:
                h.value = rule.show(v)
                self.written.add(i)
