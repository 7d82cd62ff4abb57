"""The one rule for every number typed into the panel (Label's pose, the Estimator's settings, Inspect's particles
drawn, the Data tab's ids): read as Python's ``float()`` reads it (``1e1``, ``2.5e-1``), and refuse a comma, text,
NaN, infinity and values out of the field's range with a message naming the field.

The fields are viser *text* inputs, not number inputs: the browser's number input reads what is typed its own way
(``12,5`` became 125, ``1e1`` 11, ``2.5e-1`` -2.51) and sends nothing for what it cannot read, so the server never
hears of the mistake (the sliders' own number boxes are hidden for the same reason: ``layout.without_number_box``).
``Refusals`` shows a refused value in red (``Reporter.field_errors``) and puts the value in use back once the
typing pauses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from workbench.app.ui.ui_thread import Later, UiThread
from workbench.app.ui.widgets.quiet import Quiet
from workbench.errors import InputError

REVERT_S = 1.5  # a refused typed value is put back this long after the last keystroke: sooner would fight the typing


@dataclass(frozen=True)
class NumberRule:
    """What one field accepts: a number from ``lo`` to ``hi`` (in ``unit``), a whole one if ``whole``; shown with
    ``decimals`` decimals (whole numbers with none)."""

    label: str  # the field's label: the name its errors are reported under
    lo: float
    hi: float
    unit: str = ""
    whole: bool = False
    decimals: int = 2

    @property
    def span(self) -> str:
        unit = f" {self.unit}" if self.unit and self.unit != "°" else self.unit
        kind = "a whole number" if self.whole else "a number"
        return f"{kind} from {self.lo:g} to {self.hi:g}{unit}"

    def parse(self, text: object) -> float:
        """The number typed, as ``float()`` reads it (an int if ``whole``); InputError naming the field otherwise."""
        typed = str(text).strip()
        if "," in typed:
            raise InputError(self.label, f"must be {self.span}, with a point before the decimals, not a comma; "
                                         f"got {typed!r}")
        try:
            value = float(typed)
        except ValueError:
            value = math.nan
        # Text, NaN and infinity alike; then a fraction where a count is wanted, and a value out of range.
        if not math.isfinite(value) or (self.whole and value != int(value)) or not self.lo <= value <= self.hi:
            raise InputError(self.label, f"must be {self.span}, got {typed!r}")
        return int(value) if self.whole else value

    def show(self, value: float) -> str:
        return str(int(value)) if self.whole else f"{value:.{self.decimals}f}"

    def shows(self, text: object, value: float) -> bool:
        """Whether ``text`` already reads as ``value`` (to its last bits: cm to m and back is not exact): a field the
        user typed it into is left as typed, not rewritten under the cursor."""
        try:
            typed = self.parse(text)
        except InputError:
            return False
        return abs(typed - value) <= 1e-9 * max(1.0, abs(value))


def parse_list(text: object, rules: tuple[NumberRule, ...], label: str) -> tuple[float, ...]:
    """Several numbers in one field, separated by commas (or semicolons), each read by its rule; InputError naming
    the field ``label`` (the problem names the part at fault)."""
    parts = [t.strip() for t in str(text).replace(";", ",").split(",")]
    if len(parts) != len(rules):
        what = ", ".join(r.label for r in rules)
        raise InputError(label, f"must be {len(rules)} numbers ({what}) separated by commas, got {str(text).strip()!r}")
    values = []
    for part, rule in zip(parts, rules):
        try:
            values.append(rule.parse(part))
        except InputError as err:
            raise InputError(label, f"{rule.label} {err.problem}") from None
    return tuple(values)


class Refusals:
    """Refused values of a group of fields (``ids()``: their element ids by label), shown and put back:
    ``refuse(errors)`` outlines each field in red and lists it in the banner at once (``reporter``'s
    ``field_errors``), then, once the typing pauses (REVERT_S), ``restore(labels)`` runs inside ``quiet`` to put
    the values in use back, and the reporter notifies."""

    def __init__(self, ui: UiThread, quiet: Quiet, reporter, ids: Callable[[], dict[str, str]],
                 restore: Callable[[tuple[str, ...]], None]):
        self.ui, self.quiet, self.reporter, self.ids, self.restore = ui, quiet, reporter, ids, restore
        self.refused: dict[str, str] = {}  # label -> problem, not yet put back
        self.timer: Later | None = None

    def refuse(self, errors: dict[str, str]) -> None:
        """The group's fields refused now (label -> problem); an empty dict: every field of the group reads well."""
        self.reporter.field_errors(errors, self.ids())
        self.cancel()
        self.refused = dict(errors)
        if errors:
            self.timer = self.ui.later(REVERT_S, self.put_back)

    def put_back(self) -> bool:
        """Put the values in use back into the refused fields now (they stay outlined and listed) -> whether any
        was refused."""
        self.cancel()
        refused, self.refused = self.refused, {}
        if refused:
            with self.quiet:
                self.restore(tuple(refused))
            self.reporter.refused_put_back(refused)
        return bool(refused)

    def cancel(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None


class NumberField:
    """One typed field (``handle``, a text input) read by ``rule``: a value that reads well goes to
    ``on_value(value, event)``; a refused one is shown in red and put back (``Refusals``). ``value``: the one in
    use."""

    def __init__(self, handle, rule: NumberRule, ui: UiThread, quiet: Quiet, reporter,
                 on_value: Callable[[float, object], None]):
        self.handle, self.rule, self.quiet, self.on_value = handle, rule, quiet, on_value
        self.value = rule.parse(handle.value)
        self.refusals = Refusals(ui, quiet, reporter, lambda: {rule.label: handle._impl.uuid},
                                 lambda _: self.show(self.value))
        handle.on_update(ui.callback(self.typed))

    def typed(self, event) -> None:
        if self.quiet.active:
            return  # the server showing a value, not the user typing
        try:
            value = self.rule.parse(self.handle.value)
        except InputError as err:
            self.refusals.refuse({self.rule.label: err.problem})
            return
        self.refusals.refuse({})
        self.value = value
        self.on_value(value, event)

    def show(self, value: float) -> None:
        """Show ``value`` as the one in use (no ``on_value``); a field that already reads as it keeps its text."""
        self.value = value
        if not self.rule.shows(self.handle.value, value):
            with self.quiet:
                self.handle.value = self.rule.show(value)


def resend(handle) -> None:
    """Send a GUI input's value to the browser again, unchanged (viser's setter sends only changed values): where
    the browser may show an older value than the server holds (see ``PoseFields.show``)."""
    from viser._messages import GuiUpdateMessage

    impl = handle._impl
    impl.gui_api._websock_interface.queue_message(GuiUpdateMessage(impl.uuid, {"value": impl.value}))
