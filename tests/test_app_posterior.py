"""The posterior in the workbench, without a browser: the engine settles a finished run and its
snapshot carries the posterior; the server draws the other modes as ghosts with their probabilities, shows each
object's confidence in the legend and the Inspect tab, and offers the modes in the Label tab; a session brings the
same posterior back."""

from __future__ import annotations

import numpy as np
import pytest
from headless import free_port
from inbox import Inbox

from workbench.app import protocol as p
from workbench.app.ui.run.ghosts import LABELLED
from workbench.app.ui.run.modes import confidence_text, mode_label, mode_option, posterior_markdown, scene_with_modes
from workbench.app.ui.widgets.colors import named, view_legend_html
from workbench.inference.answer.posterior import Mode, ObjectPosterior, Posterior
from workbench.inference.config import EstimatorConfig

pytestmark = pytest.mark.slow  # needs the engine: pybullet and OpenGL

CONFIG = EstimatorConfig(particles=16, iterations=2)  # three steps: the mug's hidden handle leaves modes open


def posterior_by_hand() -> Posterior:
    turned = np.diag([1.0, -1.0, -1.0, 1.0])
    turned[:3, 3] = (0.1, 0.0, 0.05)
    return Posterior([
        ObjectPosterior(0, [Mode(np.eye(4), -10.0, 0.0, 0.62, "the estimate"),
                            Mode(turned, -20.0, -10.0, 0.38, "turned over its x axis")], 0.004),
        ObjectPosterior(1, [Mode(np.eye(4), -10.0, 0.0, 1.0, "the estimate")], 0.001, (-60.0, 90.0), 0.17, 0.62),
    ], 95.0)


def test_the_posterior_in_words():
    post = posterior_by_hand()
    a, b = post.objects
    assert mode_label(a, a.modes[1]) == "p = 0.38 turned over its x axis"
    assert confidence_text(a) == "p = 0.62"
    # An object's probabilities add up as shown: the mug's one mode and elsewhere.
    assert confidence_text(b) == "p = 0.38, heading open −60° … +90°, elsewhere 0.62"
    assert mode_option(1, a, a.modes[1]) == "mode 2 · p = 0.38 · turned over its x axis"
    table = posterior_markdown(post, ["can", "mug"], 7)
    assert "iteration 7" in table
    assert f"| {named(0, 'can')} | 0.62 | p = 0.38 turned over its x axis | 0.00 (0 %) | 4.0 | — |" in table
    assert f"| {named(1, 'mug')} | 0.38 | — | 0.62 (17 %) | 1.0 | −60° … +90° |" in table
    legend = view_legend_html(["can", "mug"], "height", confidences=[confidence_text(a), ""])
    assert '<span data-confidence="0">(p = 0.62)</span>' in legend and 'data-confidence="1"' not in legend
    scene = np.stack([np.eye(4), np.eye(4)])
    chosen, notes = scene_with_modes(scene, post, (1, 0), ["can", "mug"])
    assert np.array_equal(chosen[0], a.modes[1].T) and np.array_equal(chosen[1], np.eye(4))
    assert notes == ["can: mode 2 (p = 0.38, turned over its x axis)"]
    assert np.array_equal(scene_with_modes(scene, post, (5, 3), ["can", "mug"])[0], scene)  # no such mode
    assert np.array_equal(scene_with_modes(scene, None, (1, 0), ["can", "mug"])[0], scene)


def test_a_hidden_object_is_named_hidden_with_its_places_in_words_and_as_dots_in_the_view():
    import viser

    from workbench.app.protocol import MeshData
    from workbench.app.ui.run.ghosts import ModesLayer
    from workbench.inference.answer.posterior import hidden

    places = np.array([[0.3, 0.1, 0.04], [0.325, 0.1, 0.04], [0.35, 0.1, 0.04]])
    o = hidden(ObjectPosterior(1, [Mode(np.eye(4), -10.0, 0.0, 1.0, "the estimate")], 0.001, seen_through=1.0,
                               elsewhere=0.99), places, np.zeros(3), 15.0)
    assert confidence_text(o) == "p = 0.67, hidden: one of 3 places"  # elsewhere: the region says where
    post = Posterior([posterior_by_hand().objects[0], o], 15.0)
    assert (f"| {named(1, 'mug')} | 0.67 | — | hidden: one of 3 places up to 5 cm apart, p = 0.67 where estimated | "
            f"1.0 | — |") in posterior_markdown(post, ["can", "mug"], 7)
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        box = MeshData("box", np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], np.float32),
                       np.array([[0, 1, 2]], np.int32))
        layer = ModesLayer(server)
        layer.set_frame([box, box])
        layer.update(post)
        assert sorted(layer.hiding) == [1] and sorted(layer.ghosts) == [0]
        assert np.allclose(layer.hiding[1].points, places, atol=1e-3)  # viser sends them as float16
        layer.set_visible(False)
        assert not layer.hiding[1].visible
        layer.update(None)
        assert layer.hiding == {}
    finally:
        server.stop()


def test_a_finished_run_carries_its_posterior_and_labels_take_the_chosen_mode(tmp_path, hidden_handle_dataset):
    """Snapshots carry no posterior until the run finishes; then the settled estimate's. "Use best estimate as
    label" takes the mode chosen for each object (of the posterior shown: a choice made on another iteration's
    is ignored), and settles a run that has not finished, sending the snapshot again with its posterior. A
    session saved then gives the same posterior to a new engine."""
    from workbench.app.engine.engine import Engine

    inbox, other = Inbox(), Inbox()
    engine = Engine(inbox, workers=1)
    restored = None
    try:
        engine.handle(p.Load(p.Source(dataset=hidden_handle_dataset), CONFIG, "robust"))
        K = engine.estimator.problem.n_objects
        engine.step(), engine.step()
        assert [s.posterior for s in inbox.of(p.Snapshot)] == [None, None]
        engine.step()  # iteration 2 of 2: finished, settled
        last = inbox.of(p.Snapshot)[-1]
        post, it = last.posterior, last.report["iteration"]
        assert post is not None and post is engine.estimator.posterior and len(post.objects) == K
        several = [o for o in post.objects if len(o.modes) > 1]
        assert several, "the mug's hidden handle leaves its heading open"
        k = several[0].obj
        modes = tuple(1 if j == k else 0 for j in range(K))

        engine.handle(p.UseBestAsLabel(modes, it))
        labels = inbox.of(p.Labels)[-1]
        assert np.array_equal(labels.labels[k], several[0].modes[1].T) and "mode 2" in labels.note
        assert all(np.array_equal(labels.labels[j], engine.estimator.settled[j]) for j in range(K) if j != k)
        engine.handle(p.UseBestAsLabel(modes, it - 1))  # chosen on another iteration's modes: the estimate
        assert np.array_equal(inbox.of(p.Labels)[-1].labels[k], engine.estimator.settled[k])

        engine.handle(p.SaveSession(tmp_path, "settled"))
        assert inbox.of(p.Saved)[-1].kind == "session", inbox.of(p.Failure)

        engine.handle(p.Reset(EstimatorConfig(particles=16, iterations=50), "robust"))
        engine.step()
        assert inbox.of(p.Snapshot)[-1].posterior is None  # paused mid-run: not settled
        n = len(inbox.of(p.Snapshot))
        engine.handle(p.UseBestAsLabel())
        again = inbox.of(p.Snapshot)[n:]
        assert len(again) == 1 and again[0].posterior is engine.estimator.posterior is not None

        restored = Engine(other, workers=1)
        restored.handle(p.LoadSession(tmp_path / "settled.json"))
        assert not other.of(p.Failure)
        back = other.of(p.Snapshot)[-1].posterior
        assert back is not None and back.temperature == post.temperature
        for a, b in zip(post.objects, back.objects):
            assert [(m.probability, m.what, m.gap, m.loglik) for m in a.modes] == \
                [(m.probability, m.what, m.gap, m.loglik) for m in b.modes]
            assert all(np.array_equal(m.T, n.T) for m, n in zip(a.modes, b.modes))
            assert (a.position_spread_m, a.yaw_range_deg) == (b.position_spread_m, b.yaw_range_deg)
    finally:
        engine.close()
        if restored is not None:
            restored.close()


def test_the_server_draws_the_modes_and_shows_the_confidences(hidden_handle_dataset):
    """Ghosts (an instance per other mode) with their probabilities as labels, hidden by the visibility bar's
    "modes"; the confidences in the legend and the Inspect tab; a dropdown of modes in the Label tab for the
    objects that have several; all gone after Reset."""
    from workbench.app.ui.run.view_box import visibility_item
    from workbench.app.ui.server import serve

    handle = serve(hidden_handle_dataset, block=False, port=free_port(), workers=1, config=CONFIG)
    app = handle.app
    try:
        assert app.wait_for(lambda s: s.view is not None, 180), app.state.failures
        for i in range(3):
            app.send(p.Step())
            assert app.wait_for(lambda s: s.iteration == i, 120), app.state.failures
        assert app.wait_for(lambda s: app.display.posterior is not None, 60)
        d, post = app.display, app.display.posterior
        several = [o for o in post.objects if len(o.modes) > 1]
        assert several
        app.ui.call(d.throttle.flush)
        assert sorted(d.modes.ghosts) == [o.obj for o in several]
        names = d.names
        for o in several:
            ghost = d.modes.ghosts[o.obj]
            assert len(ghost.batched_positions) == len(o.modes) - 1
            assert np.allclose(ghost.batched_positions, [m.T[:3, 3] for m in o.modes[1:]])
        assert d.modes.texts == [f"{names[o.obj]} · {mode_label(o, m)}" for o in several
                                 for m in o.modes[1:1 + LABELLED]]
        # The solid estimate is the run's settled answer (each object's top mode), not the most likely particle.
        for o, best in zip(post.objects, d.particles.best):
            assert np.allclose(best.position, o.modes[0].T[:3, 3], atol=1e-6)
        assert len(d.modes.labels) == len(d.modes.texts) and all(h.visible for h in d.modes.labels)
        for o in post.objects:
            assert f'<span data-confidence="{o.obj}">({confidence_text(o)})</span>' in app.view_box.legend.content
        assert app.display.inspect.posterior.content == posterior_markdown(post, names, 2)
        choice = app.labelling.modes
        for k, dropdown in enumerate(choice.dropdowns):
            modes = post.objects[k].modes
            assert dropdown.visible == (len(modes) > 1)
            if len(modes) > 1:
                assert tuple(dropdown.options) == tuple(mode_option(j, post.objects[k], m) for j, m in enumerate(modes))
                dropdown.value = dropdown.options[1]
        assert app.labelling.tab.modes.visible
        assert choice.chosen() == (tuple(int(len(o.modes) > 1) for o in post.objects), 2)

        app.toggle(next(o for o in app.view_box.visibility.options if visibility_item(o) == "modes"))
        assert not app.view_box.show("modes")
        assert not any(h.visible for h in (*d.modes.ghosts.values(), *d.modes.labels))
        app.toggle("○ modes")
        assert all(h.visible for h in (*d.modes.ghosts.values(), *d.modes.labels))

        app.reset()
        assert app.wait_for(lambda s: s.iteration == -1 and s.last_state.reason == "reset", 60)

        def after_reset():  # on the UI thread: nothing changes the display while this looks
            assert d.posterior is None and not d.modes.ghosts and not d.modes.labels
            assert "No posterior yet" in app.display.inspect.posterior.content and "data-confidence" not in \
                app.view_box.legend.content
            assert not app.labelling.tab.modes.visible and choice.chosen() == ((0,) * len(post.objects), -1)

        app.ui.call(after_reset)
        assert not app.state.display_errors
    finally:
        handle.stop()
