"""The run's buttons on a real viser server (no browser, no engine): a Step or a Reset that is out says so with a
spinner and keeps the other buttons from queueing behind it; a Reset pressed during a Run says it waits for the
iteration under way, is sent once however often it is pressed, and the buttons come back when the engine answers.
The sequence labels' buttons likewise wait while one of their commands is out."""

from __future__ import annotations

from workbench.app import protocol as p


def _buttons(running: list[bool]):
    import viser

    from workbench.app.ui.run.buttons import RunButtons
    from workbench.app.ui.ui_thread import UiThread

    server, ui, sent = viser.ViserServer(host="127.0.0.1", port=0, verbose=False), UiThread(), []
    buttons = ui.call(RunButtons, server.gui, ui, sent.append, lambda: running[0], lambda: None,
                      on_run=lambda: None, on_pause=lambda: None, on_reset=lambda: None)
    return server, ui, buttons, sent


def test_a_step_out_keeps_run_and_reset_from_queueing_behind_it():
    running = [False]
    server, ui, buttons, sent = _buttons(running)
    try:
        ui.call(buttons.press)
        assert [type(m) for m in sent] == [p.Step]
        assert buttons.step.disabled and buttons.run.disabled and buttons.reset.disabled
        assert buttons.busy.visible and "Step running" in buttons.busy.content
        ui.call(buttons.done)
        assert not (buttons.step.disabled or buttons.run.disabled or buttons.reset.disabled or buttons.busy.visible)
    finally:
        ui.stop()
        server.stop()


def test_a_reset_during_a_run_says_it_waits_for_the_iteration_and_is_sent_once():
    from workbench.inference.config import EstimatorConfig

    running = [True]
    server, ui, buttons, sent = _buttons(running)
    try:
        ui.call(buttons.show_running, True)
        reset = p.Reset(EstimatorConfig(), "robust")
        ui.call(buttons.press_reset, reset)
        ui.call(buttons.press_reset, reset)  # pressed again while the first waits: not sent twice
        assert sent == [reset]
        assert "Reset waits for the iteration under way" in buttons.busy.content and buttons.busy.visible
        assert buttons.reset.disabled and buttons.run.disabled and buttons.step.disabled
        running[0] = False  # the engine reset: its RunState says so
        ui.call(buttons.done)
        ui.call(buttons.show_running, False)
        assert not (buttons.busy.visible or buttons.reset.disabled or buttons.run.disabled or buttons.step.disabled)
        ui.call(buttons.press_reset, reset)  # with nothing under way
        assert "Resetting" in buttons.busy.content and len(sent) == 2
    finally:
        ui.stop()
        server.stop()


def test_the_sequence_labels_buttons_wait_for_the_engine_to_be_done_with_a_command():
    import viser

    from workbench.app.ui.labelling.sequence_labels import SequenceLabelsPanel
    from workbench.app.ui.ui_thread import UiThread

    server, ui, sent = viser.ViserServer(host="127.0.0.1", port=0, verbose=False), UiThread(), []
    try:
        panel = ui.call(SequenceLabelsPanel, server.gui, ui, sent.append, lambda: None, lambda: [])
        t = panel.tab
        buttons = (t.check, t.next_flagged, t.fit, t.save)
        assert not any(b.disabled for b in buttons)
        ui.call(panel.act, p.FitSequenceLabels(), "Fitting")
        assert sent == [p.FitSequenceLabels()] and all(b.disabled for b in buttons)
        ui.call(panel.show_progress, p.SequenceLabelProgress("frame 3 of 20"))  # still at work: still waiting
        assert all(b.disabled for b in buttons)
        ui.call(panel.show_frame, "2 ✓")  # a button group viser cannot disable: not sent, and says why
        assert sent == [p.FitSequenceLabels()] and "wait for it to finish" in t.message.content
        ui.call(panel.done, p.SequenceLabelsDone())
        assert not any(b.disabled for b in buttons)
        ui.call(panel.show_frame, "2 ✓")
        assert sent[-1] == p.ShowLabelledFrame(2) and all(b.disabled for b in buttons)
    finally:
        ui.stop()
        server.stop()
