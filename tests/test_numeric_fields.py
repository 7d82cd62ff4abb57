"""The panel's one rule for typed numbers (``widgets.numeric``): read as Python reads them, refused with a message
naming the field, put back once the typing pauses. The browser sees it in ``test_app_fields_browser``."""

from __future__ import annotations

import pytest

from workbench.app.ui.widgets.numeric import NumberRule, Refusals, parse_list
from workbench.app.ui.widgets.quiet import Quiet
from workbench.errors import InputError

X = NumberRule("x (cm)", -500, 500, "cm")
COUNT = NumberRule("Particles", 1, 100_000, whole=True)


@pytest.mark.parametrize("typed, value", [("1e1", 10.0), ("2.5e-1", 0.25), (" -3.5 ", -3.5), ("12.5", 12.5),
                                          ("1.", 1.0), (".5", 0.5), ("-500", -500.0)])
def test_numbers_read_as_python_reads_them(typed, value):
    assert X.parse(typed) == value


@pytest.mark.parametrize("typed, problem", [
    ("12,5", "not a comma"), ("abc", "got 'abc'"), ("NaN", "got 'NaN'"), ("nan", "got 'nan'"), ("inf", "got 'inf'"),
    ("-Infinity", "got '-Infinity'"), ("", "got ''"), ("1e9", "got '1e9'"), ("500.01", "from -500 to 500 cm"),
    ("1e", "got '1e'"), ("-", "got '-'"),
])
def test_a_comma_text_nan_infinity_and_out_of_range_are_refused_naming_the_field(typed, problem):
    with pytest.raises(InputError) as err:
        X.parse(typed)
    assert err.value.path == "x (cm)" and problem in err.value.problem, err.value.problem


def test_whole_numbers_take_any_spelling_of_a_whole_value():
    assert COUNT.parse("1e3") == 1000 and isinstance(COUNT.parse("1e3"), int)
    assert COUNT.parse("64.0") == 64
    for typed in ("2.5", "0", "1e6", "12,5"):
        with pytest.raises(InputError, match="whole number from 1 to 100000"):
            COUNT.parse(typed)


def test_shown_values_read_back_and_a_field_reading_as_its_value_keeps_its_text():
    assert X.show(1.23456) == "1.23" and COUNT.show(64) == "64"
    assert X.shows("1.", 1.0) and X.shows("1e1", 10.0) and X.shows("1.5", 0.015 * 100.0)
    assert not X.shows("1.23", 1.23456) and not X.shows("abc", 0.0)


def test_lists_read_each_part_by_its_rule():
    rules = (NumberRule("x", 0, 100, "cm"), NumberRule("y", 0, 100, "cm"))
    assert parse_list("1, 2.5e-1", rules, "σ x, y (cm)") == (1.0, 0.25)
    assert parse_list("1; 2", rules, "σ x, y (cm)") == (1.0, 2.0)
    for typed, problem in (("1", "2 numbers (x, y)"), ("1, abc", "y must be a number from 0 to 100 cm, got 'abc'"),
                           ("1, 1e9", "y must be"), ("nan, 1", "x must be")):
        with pytest.raises(InputError) as err:
            parse_list(typed, rules, "σ x, y (cm)")
        assert err.value.path == "σ x, y (cm)" and problem in err.value.problem, err.value.problem


class FakeUi:
    def __init__(self):
        self.timers = []

    def later(self, delay, fn):
        class Later:
            def cancel(later):
                self.timers.remove(entry)
        entry = (delay, fn)
        self.timers.append(entry)
        return Later()


class FakeReporter:
    def __init__(self):
        self.shown, self.put_back = [], []

    def field_errors(self, errors, ids):
        self.shown.append(dict(errors))

    def refused_put_back(self, refused):
        self.put_back.append(dict(refused))


def test_a_refused_value_is_shown_at_once_and_put_back_quietly_once_the_typing_pauses():
    ui, quiet, reporter, restored = FakeUi(), Quiet(), FakeReporter(), []
    refusals = Refusals(ui, quiet, reporter, lambda: {"x (cm)": "id-x"},
                        lambda labels: restored.append((labels, quiet.active)))
    refusals.refuse({"x (cm)": "must be ..."})
    assert reporter.shown == [{"x (cm)": "must be ..."}] and not restored and len(ui.timers) == 1
    refusals.refuse({"x (cm)": "must be ... again"})  # still typing: one timer, from the last keystroke
    assert len(ui.timers) == 1
    ui.timers[0][1]()
    assert restored == [(("x (cm)",), True)] and reporter.put_back == [{"x (cm)": "must be ... again"}]
    assert not refusals.put_back()  # nothing left to put back
    refusals.refuse({"x (cm)": "bad"})
    refusals.refuse({})  # corrected before the pause: nothing is put back
    assert not ui.timers and reporter.shown[-1] == {} and len(restored) == 1


def test_each_group_of_fields_keeps_its_own_refusals_in_the_banner():
    import viser

    from workbench.app.ui.reporting import Reporter
    from workbench.app.ui.run.status import RunView

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        reporter = Reporter(server, RunView)
        reporter.field_errors({"Particles": "must be a whole number"}, {"Particles": "p-id", "Seed": "s-id"})
        reporter.field_errors({"x (cm)": "must be a number"}, {"x (cm)": "x-id", "y (cm)": "y-id"})
        assert "p-id" in reporter.field_style.content and "x-id" in reporter.field_style.content
        assert "2 problems" in reporter.error.content and reporter.error.visible
        reporter.field_errors({}, {"x (cm)": "x-id", "y (cm)": "y-id"})  # the label's fields corrected
        assert "x-id" not in reporter.field_style.content and "p-id" in reporter.field_style.content
        assert "Particles" in reporter.error.content and "x (cm)" not in reporter.error.content
    finally:
        server.stop()


def test_label_pose_fields_pass_on_what_reads_well_and_leave_a_field_being_typed_alone():
    import numpy as np
    import viser

    from workbench.app.ui.labelling.controls import build_label_tab
    from workbench.app.ui.labelling.pose_fields import PoseFields
    from workbench.app.ui.ui_thread import UiThread
    from workbench.geometry import make_pose

    server, ui, quiet, reporter, typed = viser.ViserServer(port=0, verbose=False), UiThread(), Quiet(), \
        FakeReporter(), []
    try:
        tab = build_label_tab(server.gui)
        fields = ui.call(PoseFields, tab, ui, quiet, reporter, lambda i, v: typed.append((i, v)))

        def show(xyz):  # as the editor shows a pose: on the UI thread, quietly
            def quietly():
                with quiet:
                    fields.show(make_pose(np.eye(3), xyz))
            ui.call(quietly)

        show([0.01, 0.02, 0.03])
        assert [h.value for h in tab.position] == ["1.00", "2.00", "3.00"] and tab.angles[2].value == "0.00"
        tab.position[0].value = "-"  # as the browser sends a keystroke: on its way to "-3", refused until then
        assert typed == [] and "x (cm)" in reporter.shown[-1]
        show([0.05, 0.02, 0.03])  # the run's estimate moves the object: the field being typed into keeps its text
        assert tab.position[0].value == "-" and fields.values[0] == 5.0
        tab.position[0].value = "-3"
        tab.angles[2].value = "1e1"
        assert typed == [(0, -3.0), (5, 10.0)] and reporter.shown[-1] == {}
        assert list(fields.angles_with(5, 10.0)) == [0.0, 0.0, 10.0]
    finally:
        ui.stop()
        server.stop()


def test_a_pose_field_typed_as_the_server_wrote_it_is_sent_again_once_the_typing_pauses():
    """A new frame's labels written to the x field and a keystroke crossing them: the browser may show the written
    value while the server holds the typed one. The held value goes to the browser again after the typing pauses;
    a field the server had not written since is left to the browser."""
    import time

    import numpy as np
    import viser
    from viser._messages import GuiUpdateMessage

    from workbench.app.ui.labelling.controls import build_label_tab
    from workbench.app.ui.labelling.pose_fields import PoseFields
    from workbench.app.ui.ui_thread import UiThread
    from workbench.app.ui.widgets.numeric import REVERT_S
    from workbench.geometry import make_pose

    server, ui, quiet, reporter, typed = viser.ViserServer(port=0, verbose=False), UiThread(), Quiet(), \
        FakeReporter(), []
    sent: list[tuple[str, object]] = []
    interface = server.gui._websock_interface
    queue = interface.queue_message

    def recording(message):  # the real queue, its messages to the browser also listed here
        if isinstance(message, GuiUpdateMessage) and "value" in message.updates:
            sent.append((message.uuid, message.updates["value"]))
        queue(message)

    interface.queue_message = recording
    try:
        tab = build_label_tab(server.gui)
        fields = ui.call(PoseFields, tab, ui, quiet, reporter, lambda i, v: typed.append((i, v)))
        x, y = (h._impl.uuid for h in tab.position[:2])

        def show(xyz):
            def quietly():
                with quiet:
                    fields.show(make_pose(np.eye(3), xyz))
            ui.call(quietly)

        show([0.01, 0.02, 0.03])  # the new frame's labels, written to every field
        assert (x, "1.00") in sent
        tab.position[0].value = "-2"  # keystrokes sent before the browser had the write
        tab.position[0].value = "-2.01"
        sent.clear()  # setting the values here sent them, as the browser's keystrokes would not
        time.sleep(REVERT_S / 2)
        assert ui.call(lambda: sent) == []  # not while the typing may go on
        assert ui.wait_until(lambda: (x, "-2.01") in sent, 5 * REVERT_S), sent
        assert typed == [(0, -2.0), (0, -2.01)]
        # Typed again with no write in between: the browser already shows what it sent.
        tab.position[0].value = "-2.5"
        sent.clear()  # setting the value here sent it, as the browser's keystroke would not
        time.sleep(2 * REVERT_S)
        assert ui.call(lambda: sent) == [] and typed[-1] == (0, -2.5)
        assert tab.position[1].value == "2.00" and (y, "2.00") not in sent
    finally:
        ui.stop()
        server.stop()
