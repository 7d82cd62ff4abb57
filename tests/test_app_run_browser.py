"""The browser workbench in real headless Chromium: one demo server and one browser for the whole module."""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import pytest
from headless import (
    FRAME_PROBE_JS,
    SentMessages,
    canvas_png,
    chromium_path,
    color_extent,
    frame_counts,
    gui_input,
    image_stats,
    open_workbench,
    served,
)

from workbench.app.engine.snapshot import DEFAULT_DISPLAY
from workbench.app.protocol import Failure, Run
from workbench.app.ui.run.display import SCENE_INTERVAL_S
from workbench.io.results import ResultRow, read_results_csv, write_results_csv

pytest.importorskip("playwright.sync_api")
from playwright.sync_api import expect  # noqa: E402

pytestmark = [pytest.mark.slow,  # needs Chromium, and the engine: pybullet and OpenGL
              pytest.mark.skipif(chromium_path() is None, reason="no system Chromium (Debian package `chromium`)")]

TIMEOUT_MS = 60_000
# Software WebGL redraws the whole canvas on every change: a smaller page keeps two tabs responsive on 2 cores.
VIEWPORT = {"width": 1000, "height": 700}


@pytest.fixture(scope="module")
def sessions_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("sessions")
    (d / "damaged.json").write_text('{"format_version": 1, "kind": "workbench-session", "frame": ')  # cut short
    return d


@pytest.fixture(scope="module")
def workbench(sessions_dir):
    from workbench.inference.config import EstimatorConfig

    with served(EstimatorConfig(particles=48, iterations=500), demo=True, sessions_dir=sessions_dir) as handle:
        yield handle


@pytest.fixture(scope="module")
def browser():
    from headless import chromium

    with chromium() as b:
        yield b


@pytest.fixture(scope="module")
def page(browser, workbench):
    p = open_workbench(browser, workbench.url, TIMEOUT_MS, VIEWPORT, init_script=FRAME_PROBE_JS)
    yield p
    p.close()


def iteration_text(i: int) -> re.Pattern:
    return re.compile(rf"Iteration {i} of \d+")


def step(page, app) -> int:
    """Click Step and wait until this page shows the next iteration -> that iteration."""
    nxt = app.state.iteration + 1
    page.get_by_role("button", name="Step").click()
    page.get_by_text(iteration_text(nxt)).wait_for(timeout=TIMEOUT_MS)
    return nxt


BEST_LINE = (0xE8, 0x59, 0x0C)  # plots.py: the best log-likelihood's colour


def assert_plots_draw_lines(page, app) -> None:
    """The Plots tab's first chart (log-likelihood) draws its "best" line across most of its width."""
    page.get_by_role("tab", name="Plots").click()
    chart = page.locator(".uplot").first
    chart.wait_for(timeout=TIMEOUT_MS)
    deadline = time.monotonic() + 60
    while True:  # software WebGL and uPlot's layout take a moment
        count, span = color_extent(chart.screenshot(), BEST_LINE)
        if (count > 30 and span > 0.5) or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    assert count > 30 and span > 0.5, (count, span, len(app.state.reports))
    expect(page.get_by_text("tempering exponent β")).to_be_visible(timeout=TIMEOUT_MS)
    expect(page.get_by_text("distinct particles after resampling")).to_be_visible(timeout=TIMEOUT_MS)


def test_page_shows_the_demo_scene(page, workbench):
    page.get_by_text(re.compile(r"demo · scene \d+ · frame \d+")).wait_for(timeout=TIMEOUT_MS)
    deadline = time.monotonic() + 30
    while True:  # SwiftShader on a loaded machine can take seconds to draw the first frames
        std, drawn = image_stats(canvas_png(page))
        if (std > 5.0 and drawn > 0.05) or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    # A blank canvas is one colour; the point cloud, table and camera cover a good part of the view.
    assert std > 5.0 and drawn > 0.05, (std, drawn)


def test_step_advances_the_iteration_and_moves_the_particles(page, workbench):
    app = workbench.app
    step(page, app)
    before = np.array(app.display.particles.batches[0].batched_positions)
    step(page, app)
    after = np.array(app.display.particles.batches[0].batched_positions)
    assert before.shape == after.shape == (min(48, DEFAULT_DISPLAY), 3)
    assert not np.allclose(before, after)
    # The chosen particle's panel and heatmap followed.
    assert app.state.chosen is not None and app.state.chosen.iteration == app.state.iteration


def test_inspecting_a_particle_shows_its_heatmap_and_what_physics_changed(page, workbench):
    app = workbench.app
    if app.state.iteration < 0:
        step(page, app)
    page.get_by_role("tab", name="Inspect").click()
    # Shared GUI state: set on the server (as another tab would), followed by this page.
    app.display.inspect.heatmap_mode.value = "log-likelihood"
    page.get_by_text(re.compile(r"log-likelihood \(per pixel\), particle rank 0")).wait_for(timeout=TIMEOUT_MS)
    assert not app.display.points_visible()  # the heatmap replaces the observed points
    app.display.inspect.rank.value = 3
    page.get_by_text(re.compile(r"Rank 3 \(particle \d+\)")).wait_for(timeout=TIMEOUT_MS)
    app.display.inspect.heatmap_mode.value = "residual"
    app.display.inspect.scene_mode.value = "side by side"
    page.get_by_text(re.compile(r"residual \(cm\), particle rank 3")).wait_for(timeout=TIMEOUT_MS)
    assert app.display.chosen.before[0].visible and app.display.chosen.after[0].visible
    app.pick(2)  # what clicking the third most likely particle in the 3D view does
    page.get_by_text(re.compile(r"Rank 2 \(particle \d+\)")).wait_for(timeout=TIMEOUT_MS)
    app.display.inspect.heatmap_mode.value = "off"
    app.display.inspect.scene_mode.value = "before + after"
    app.pick(0)
    assert app.display.points_visible()
    page.get_by_role("tab", name="Estimator").click()


def test_run_then_pause_stops_within_one_iteration(page, workbench):
    app = workbench.app
    start = app.state.iteration
    page.get_by_role("button", name="Run").click()
    assert app.wait_for(lambda s: s.iteration >= start + 3, 120), "Run did not iterate"
    page.get_by_role("button", name="Pause").click()
    assert app.wait_for(lambda s: s.last_state is not None and s.last_state.reason == "paused", 60)
    stopped = app.state.last_state.iteration
    assert stopped <= app.state.pause_requested_at + 1, (stopped, app.state.pause_requested_at)
    page.get_by_text(re.compile(rf"Iteration {stopped} of \d+ · paused")).wait_for(timeout=TIMEOUT_MS)
    time.sleep(1.5)
    assert app.state.iteration == stopped  # nothing ran after the pause


def test_the_3d_view_is_redrawn_at_most_once_an_interval_while_running_and_not_at_all_when_paused(page, workbench):
    app = workbench.app
    start = app.state.iteration
    with SentMessages().record() as sent:
        t_run = time.monotonic()
        # Run past convergence: the run must last long enough for a few redraws (the Run button stops at
        # convergence, which the demo reaches within seconds).
        app.send(Run(stop_on_convergence=False))
        assert app.wait_for(lambda s: s.iteration >= start + 3, 120), "Run did not iterate"
        time.sleep(max(0.0, t_run + 4 * SCENE_INTERVAL_S - time.monotonic()))
        t_pause = time.monotonic()  # later, the run's end is drawn at once
        page.get_by_role("button", name="Pause").click()
        assert app.wait_for(lambda s: not s.running and s.last_state.reason == "paused", 60)
        time.sleep(1.0)  # the frames that draw where the run stopped
        f0, t0 = frame_counts(page), time.monotonic()
        time.sleep(4.0)
        f1, t1 = frame_counts(page), time.monotonic()
        redraws = sent.redraws(t_run, t_pause)
        idle = sent.scene_since(t0, t1)
    # Every iteration updates the panel, but the 3D view only every SCENE_INTERVAL_S (a little slack for the event
    # loop's scheduling).
    assert len(redraws) >= 2, redraws
    assert min(np.diff(redraws)) > SCENE_INTERVAL_S - 0.15, np.diff(redraws)
    # Paused: nothing changes, so nothing is sent, and the page draws only viser's heartbeat frame a second.
    assert idle == [], idle
    assert f1["frames"] - f0["frames"] <= (t1 - t0) * 1.0 + 2, (f0, f1)
    assert f1["animations"] == 0, f1


def test_plots_draw_lines_after_reset(page, workbench):
    app = workbench.app
    page.get_by_role("tab", name="Estimator").click()
    page.get_by_role("button", name="Reset").click()
    assert app.wait_for(lambda s: s.iteration == -1 and s.last_state is not None and s.last_state.reason == "reset", 60)
    page.get_by_text(re.compile(r"No iterations yet")).first.wait_for(timeout=TIMEOUT_MS)
    for _ in range(4):
        step(page, app)
    assert_plots_draw_lines(page, app)
    page.get_by_role("tab", name="Estimator").click()


def test_the_legend_names_every_colour_and_the_objects(page, workbench):
    legend = page.locator('[data-legend="3d-view"]')
    if not legend.is_visible():
        page.get_by_text("Legend", exact=True).click()  # folded by default: the panel's top stays short
    expect(legend).to_be_visible(timeout=TIMEOUT_MS)
    for text in ("particles", "most likely scene", "before physics", "label", "ground truth", "object region",
                 "depth sensor", "observed points"):
        expect(legend).to_contain_text(text)
    for name in (m.name for m in workbench.app.state.view.meshes):
        expect(legend).to_contain_text(name)


def test_refused_values_are_put_back_outlined_and_all_listed(page, workbench):
    """Bug: Particles -5 and σ x, y "abc" stayed on screen while the run used 128 and 1, and the banner showed only
    the newest error."""
    app = workbench.app
    page.get_by_role("tab", name="Estimator").click()
    in_use = str(app.config.particles)
    particles = gui_input(page, "Particles")
    particles.fill("-5")
    particles.press("Enter")
    sigma = gui_input(page, "σ x, y (cm)")
    sigma.fill("abc")
    sigma.press("Enter")
    banner = page.get_by_text(re.compile(r"2 problems"))
    banner.first.wait_for(timeout=TIMEOUT_MS)
    listed = page.locator(".mantine-List-itemLabel")  # the banner's list, not the notifications
    expect(listed.filter(has_text=re.compile(r"Particles.*whole number.*-5"))).to_be_visible(timeout=TIMEOUT_MS)
    expect(listed.filter(has_text=re.compile(r"σ x, y \(cm\).*'abc'"))).to_be_visible(timeout=TIMEOUT_MS)
    # The fields show the values in use again, outlined.
    expect(particles).to_have_value(in_use, timeout=TIMEOUT_MS)
    expect(sigma).to_have_value(re.compile(r"^\d"), timeout=TIMEOUT_MS)
    outline = particles.evaluate("e => getComputedStyle(e).outlineStyle")
    assert outline == "solid", outline
    assert app.config.particles == int(in_use)
    step(page, app)  # an iteration went through: the problems are dealt with
    expect(banner.first).to_be_hidden(timeout=TIMEOUT_MS)
    expect(particles).to_have_value(in_use)
    # A corrected value clears its line; the diffusion's error speaks the field's units (cm).
    app.settings.tab.sigma_z.value = "-1"  # as another tab would type it
    banner = page.get_by_text(re.compile(r"σ elevation \(cm\).*from 0 to 100 cm, got '-1'"))
    banner.first.wait_for(timeout=TIMEOUT_MS)
    z = gui_input(page, "σ elevation (cm)")
    z.fill("1")
    z.press("Enter")
    expect(banner.first).to_be_hidden(timeout=TIMEOUT_MS)
    # An error from the engine clears once an iteration goes through.
    app.ui.call(app.reporter.report, Failure("Input error", "a test problem"))
    banner = page.get_by_text("a test problem")
    banner.first.wait_for(timeout=TIMEOUT_MS)
    step(page, app)
    expect(banner.first).to_be_hidden(timeout=TIMEOUT_MS)


def test_reset_clears_the_old_run_from_the_view_and_the_tables(page, workbench):
    """Bug: after Reset the old estimate, the inspected particle's wireframe and the stage timings stayed."""
    app = workbench.app
    page.get_by_role("tab", name="Estimator").click()
    step(page, app)
    app.pick(3)
    assert app.wait_for(lambda s: s.chosen is not None and s.chosen.rank == 3, 60)
    page.get_by_role("cell", name="projection").wait_for(timeout=TIMEOUT_MS)  # the timings table
    page.get_by_text("Estimate vs ground truth").wait_for(timeout=TIMEOUT_MS)
    step(page, app)
    page.get_by_role("button", name="Reset").click()
    assert app.wait_for(lambda s: s.iteration == -1 and s.last_state.reason == "reset", 60)
    page.get_by_text(re.compile(r"No iterations yet")).first.wait_for(timeout=TIMEOUT_MS)
    expect(page.get_by_role("cell", name="projection")).to_have_count(0, timeout=TIMEOUT_MS)
    expect(page.get_by_text("Estimate vs ground truth")).to_have_count(0, timeout=TIMEOUT_MS)
    d = app.display
    assert not d.particles.best and not d.particles.batches  # no estimate, no particles
    assert not any(h.visible for h in d.chosen.before + d.chosen.after)  # no inspected particle
    assert not d.chosen.extras.handles and not d.heatmap.nodes.handles
    app.pick(0)
    step(page, app)


def test_session_name_error_keeps_its_underscores(page, workbench):
    """Bug: the session-name error lost its underscores ('_' was read as Markdown emphasis)."""
    page.get_by_role("tab", name="Sessions").click()
    name = gui_input(page, "Session name")
    name.fill("no good!")
    name.press("Enter")
    page.get_by_role("button", name="Save session").click()
    expect(page.get_by_text("'.', '_' or '-'", exact=False).first).to_be_visible(timeout=TIMEOUT_MS)
    page.get_by_role("tab", name="Estimator").click()


def test_turning_the_heatmap_off_leaves_the_points_as_they_were(page, workbench):
    """Bug: turning the heatmap off turned Observed points back on, even when they were off."""
    app = workbench.app
    if app.state.iteration < 0:
        step(page, app)
    bar = page.get_by_role("button", name=re.compile(r"^[●○] points$"))
    bar.click()
    expect(page.get_by_role("button", name="○ points")).to_be_visible(timeout=TIMEOUT_MS)
    assert app.wait_for(lambda s: not app.view_box.show("points"), 10)
    page.get_by_role("tab", name="Inspect").click()
    app.display.inspect.heatmap_mode.value = "residual"  # shared GUI state, as another tab would choose it
    page.get_by_text(re.compile(r"residual \(cm\), particle rank")).wait_for(timeout=TIMEOUT_MS)
    app.display.inspect.heatmap_mode.value = "off"
    expect(page.get_by_role("button", name="○ heatmap")).to_be_visible(timeout=TIMEOUT_MS)
    assert not app.view_box.show("points") and not any(h.visible for h in app.display.observation.clouds)
    page.get_by_role("button", name="○ points").click()
    assert app.wait_for(lambda s: all(h.visible for h in app.display.observation.clouds), 10)
    page.get_by_role("tab", name="Estimator").click()


def test_the_visibility_bar_shows_and_hides_each_layer(page, workbench):
    app = workbench.app
    if app.state.iteration < 0:
        step(page, app)
    d = app.display
    layers = {
        "points": lambda: d.observation.clouds,
        "particles": lambda: d.particles.batches,
        "estimate": lambda: d.particles.best,
        "truth": lambda: d.observation.gt,
    }
    assert d.observation.gt, "the demo has ground truth"
    for item, handles in layers.items():
        page.get_by_role("button", name=f"● {item}").click()  # shown by default: hide
        expect(page.get_by_role("button", name=f"○ {item}")).to_be_visible(timeout=TIMEOUT_MS)
        assert app.wait_for(lambda s: not any(h.visible for h in handles()), 10), item
        page.get_by_role("button", name=f"○ {item}").click()
        expect(page.get_by_role("button", name=f"● {item}")).to_be_visible(timeout=TIMEOUT_MS)
        assert app.wait_for(lambda s: all(h.visible for h in handles()), 10), item
    page.get_by_role("button", name="○ heatmap").click()
    expect(page.get_by_role("button", name="● heatmap")).to_be_visible(timeout=TIMEOUT_MS)
    assert app.display.inspect.heatmap_mode.value != "off" and not app.display.points_visible()  # the mode last used
    page.get_by_role("button", name="● heatmap").click()
    expect(page.get_by_role("button", name="○ heatmap")).to_be_visible(timeout=TIMEOUT_MS)
    assert app.display.inspect.heatmap_mode.value == "off" and app.display.points_visible()
    page.get_by_role("button", name="● labels").click()
    expect(page.get_by_role("button", name="○ labels")).to_be_visible(timeout=TIMEOUT_MS)
    assert not app.labelling.editor.shown
    page.get_by_role("button", name="○ labels").click()
    expect(page.get_by_role("button", name="● labels")).to_be_visible(timeout=TIMEOUT_MS)


def test_the_truth_table_agrees_with_workbench_score(page, workbench, tmp_path):
    """The per-object errors against scene_gt.json, as shown, are what `workbench score` says of the same estimate."""
    from workbench.score.scoring import score_results

    app = workbench.app
    step(page, app)
    assert app.wait_for(lambda s: s.truth is not None and s.truth.iteration == s.iteration, 60)
    truth = app.state.truth
    table = page.get_by_text("Estimate vs ground truth")
    table.wait_for(timeout=TIMEOUT_MS)
    right = re.compile(rf"iteration {truth.iteration} · \d+/\d+ right")
    expect(page.get_by_text(right)).to_be_visible(timeout=TIMEOUT_MS)
    view = app.state.view
    scene_id, im_id = view.where[1], view.where[2]
    T_cam_world = np.linalg.inv(view.T_world_cam)
    obj_ids = [r["obj_id"] for r in truth.rows]
    rows = [ResultRow(scene_id, im_id, o, 1.0, T_cam_world @ T, -1.0) for o, T in zip(obj_ids, truth.estimate)]
    csv = tmp_path / "results.csv"
    write_results_csv(csv, rows)
    scored = score_results(Path(view.where[0]), read_results_csv(csv))[0].objects
    for shown, ref in zip(truth.rows, scored):
        assert shown["obj_id"] == ref.obj_id and shown["right"] == ref.right
        assert np.isclose(shown["position_cm"], ref.position_cm, atol=1e-6)
        assert np.isclose(shown["rotation_deg"], ref.rotation_deg, atol=1e-4)
        assert np.isclose(shown["add_s_mm"], ref.add_s_mm, atol=1e-4)
        # ... and the page shows those numbers.
        page.get_by_role("cell", name=f"{ref.position_cm:.2f}", exact=True).first.wait_for(timeout=TIMEOUT_MS)
        page.get_by_role("cell", name=f"{ref.add_s_mm:.1f}", exact=True).first.wait_for(timeout=TIMEOUT_MS)


def test_a_running_step_shows_a_spinner_and_disables_step(page, workbench):
    app = workbench.app
    page.get_by_role("tab", name="Estimator").click()
    field = gui_input(page, "Particles")
    field.fill("600")  # a slow step, long enough to see
    field.press("Enter")
    assert app.wait_for(lambda s: app.config.particles == 600, 30)
    nxt = app.state.iteration + 1
    button = page.get_by_role("button", name="Step")
    button.click()
    expect(page.get_by_text(re.compile(r"Step running · \d+ s"))).to_be_visible(timeout=TIMEOUT_MS)
    expect(button).to_be_disabled(timeout=TIMEOUT_MS)
    page.get_by_text(iteration_text(nxt)).wait_for(timeout=TIMEOUT_MS)
    expect(button).to_be_enabled(timeout=TIMEOUT_MS)
    expect(page.get_by_text(re.compile(r"Step running"))).to_have_count(0, timeout=TIMEOUT_MS)
    field.fill("48")
    field.press("Enter")
    assert app.wait_for(lambda s: app.config.particles == 48, 30)


def test_bad_dataset_path_shows_an_error_and_the_page_keeps_working(page, workbench):
    app = workbench.app
    bad = "/nonexistent/bop_dataset_xyz"
    page.get_by_role("tab", name="Data").click()
    field = gui_input(page, "Dataset")
    field.fill(bad)
    field.press("Enter")
    page.get_by_role("button", name="Load dataset").click()
    page.get_by_text(re.compile(re.escape(bad) + r".*no such file")).first.wait_for(timeout=TIMEOUT_MS)
    assert any(f.path == bad for f in app.state.failures)
    assert app.state.view is not None and "demo" in app.state.view.title  # the demo is still loaded
    page.get_by_role("tab", name="Estimator").click()
    step(page, app)


def test_two_tabs_see_the_same_run(browser, page, workbench):
    app = workbench.app
    if app.state.iteration < 0:
        step(page, app)
    other = open_workbench(browser, workbench.url, TIMEOUT_MS, VIEWPORT)
    try:
        shown = app.state.iteration
        other.get_by_text(iteration_text(shown)).wait_for(timeout=TIMEOUT_MS)
        nxt = step(other, app)  # driven from the second tab ...
        page.get_by_text(iteration_text(nxt)).wait_for(timeout=TIMEOUT_MS)  # ... seen in the first
        # Settings are shared too: a particle count typed in one tab shows in the other and drives the run.
        field = gui_input(other, "Particles")
        field.fill("40")
        field.press("Enter")
        assert app.wait_for(lambda s: app.config.particles == 40, 30)
        expect(gui_input(page, "Particles")).to_have_value("40", timeout=TIMEOUT_MS)
        nxt = step(page, app)
        assert app.wait_for(lambda s: s.cloud is not None and s.cloud.n_total == 40, 30)
        other.get_by_text(iteration_text(nxt)).wait_for(timeout=TIMEOUT_MS)
    finally:
        other.close()


LABEL_FIELDS = ("x (cm)", "y (cm)", "z (cm)", "roll (°)", "pitch (°)", "yaw (°)")


def test_label_snap_save_session_reload_and_load_it(page, workbench):
    """Label an object by typing, snap it, save the session; spoil the label, reload the page, load the session:
    the label (and the run) come back as saved."""
    app = workbench.app
    while app.state.iteration < 2:  # a history of a few iterations, for the plots to draw as lines
        step(page, app)
    page.get_by_role("tab", name="Label").click()
    z = gui_input(page, "z (cm)")
    z.fill("9")
    z.press("Enter")
    editor = app.labelling.editor
    assert app.wait_for(lambda s: editor.labels[0] is not None and editor.labels[0][2, 3] == 0.09, 30)
    page.get_by_role("button", name="Snap to plausible").click()
    page.get_by_text("Snapped").first.wait_for(timeout=TIMEOUT_MS)
    snapped = app.labelling.editor.labels[0].copy()
    assert snapped[2, 3] < 0.085  # it fell onto the table (or the other object)
    expect(z).not_to_have_value(re.compile(r"^9(\.0*)?$"), timeout=TIMEOUT_MS)
    shown = {name: gui_input(page, name).input_value() for name in LABEL_FIELDS}
    # With a label present, the estimate's errors against it are shown.
    page.get_by_text("Best estimate vs label").wait_for(timeout=TIMEOUT_MS)

    page.get_by_role("tab", name="Sessions").click()
    name = gui_input(page, "Session name")
    name.fill("labelled")
    name.press("Enter")
    page.get_by_role("button", name="Save session").click()
    page.get_by_text(re.compile(r"Saved session labelled")).wait_for(timeout=TIMEOUT_MS)
    saved_iteration = app.state.iteration

    # Spoil the label and advance the run, then come back with a fresh page.
    page.get_by_role("tab", name="Label").click()
    x = gui_input(page, "x (cm)")
    x.fill("3")
    x.press("Enter")
    assert app.wait_for(lambda s: app.labelling.editor.labels[0][0, 3] == 0.03, 30)
    step(page, app)
    page.reload()
    page.get_by_role("button", name="Step").wait_for(timeout=TIMEOUT_MS)
    page.get_by_role("tab", name="Sessions").click()
    assert app.sessions.tab.choice.value == "labelled"  # the save selected it
    page.get_by_role("button", name="Load session").click()
    # The run went on past the save: loading would lose that, so the tab asks first.
    page.get_by_text("The current run is not saved").wait_for(timeout=TIMEOUT_MS)
    page.get_by_role("button", name="Load anyway").click()
    page.get_by_text(re.compile(r"Loaded session labelled at iteration")).wait_for(timeout=TIMEOUT_MS)
    assert app.state.iteration == saved_iteration
    assert np.array_equal(app.labelling.editor.labels[0], snapped)
    page.get_by_role("tab", name="Label").click()
    for field_name, value in shown.items():
        expect(gui_input(page, field_name)).to_have_value(value, timeout=TIMEOUT_MS)
    assert_plots_draw_lines(page, app)  # the restored history
    nxt = step(page, app)  # and the restored run goes on
    assert nxt == saved_iteration + 1


def test_dragging_a_gizmo_labels_the_object_and_moves_its_fields(page, workbench):
    import viser

    app = workbench.app
    page.get_by_role("tab", name="Label").click()
    app.labelling.tab.object.value = app.labelling.editor.names[1]  # shared GUI state, as another tab would choose it
    gizmo = app.labelling.editor.gizmos[1]
    assert gizmo.visible
    # What viser does when a browser drags the gizmo: the handle takes the pose, then the callbacks run.
    gizmo.position = (0.0123, -0.0456, 0.05)
    event = viser.TransformControlsEvent(client=None, client_id=None, target=gizmo, phase="end")
    app.labelling.editor.gizmo_moved(1, event)
    assert np.allclose(app.labelling.editor.labels[1][:3, 3], (0.0123, -0.0456, 0.05))
    expect(gui_input(page, "x (cm)")).to_have_value(re.compile(r"^1\.23"), timeout=TIMEOUT_MS)
    expect(gui_input(page, "y (cm)")).to_have_value(re.compile(r"^-4\.56"), timeout=TIMEOUT_MS)
    page.get_by_role("button", name="Clear label").click()
    assert app.wait_for(lambda s: app.labelling.editor.labels[1] is None, 30)


def test_a_damaged_session_shows_its_problem_and_the_run_goes_on(page, workbench):
    app = workbench.app
    page.get_by_role("tab", name="Sessions").click()
    page.get_by_text(re.compile(r"damaged — ⚠ cannot be loaded: corrupt session file")).wait_for(timeout=TIMEOUT_MS)
    app.sessions.tab.choice.value = "damaged"  # shared GUI state, as another tab would choose it
    unsaved = app.sessions.unsaved() is not None
    page.get_by_role("button", name="Load session").click()
    if unsaved:  # the current run is not saved: asked first
        page.get_by_text("The current run is not saved").wait_for(timeout=TIMEOUT_MS)
        page.get_by_role("button", name="Load anyway").click()
    page.get_by_text(re.compile(r"damaged\.json: corrupt session file")).first.wait_for(timeout=TIMEOUT_MS)
    assert any(f.topic == "session" and f.path.endswith("damaged.json") for f in app.state.failures)
    step(page, app)


def test_every_place_shows_the_objects_by_name(page, workbench):
    """Legend (above), Inspect's physics table, the Label tab's object list and its error table: one name each."""
    app = workbench.app
    names = [m.name for m in app.state.view.meshes]
    assert names == ["foam_brick", "wood_block"], names  # the demo's models_info.json names its models
    if app.state.iteration < 0:
        step(page, app)
    page.get_by_role("tab", name="Inspect").click()
    for name in names:
        page.get_by_role("cell", name=name, exact=True).first.wait_for(timeout=TIMEOUT_MS)
    page.get_by_role("tab", name="Label").click()
    assert list(app.labelling.tab.object.options) == names
    page.get_by_role("button", name="Use best estimate as label").click()
    page.get_by_text("Best estimate vs label").wait_for(timeout=TIMEOUT_MS)
    for name in names:
        page.get_by_role("cell", name=name, exact=True).first.wait_for(timeout=TIMEOUT_MS)
    assert not page.get_by_text(re.compile(r"\bobj \d+\b")).count()  # the old "obj 6" form is gone
