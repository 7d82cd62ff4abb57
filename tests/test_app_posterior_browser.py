"""The posterior in real headless Chromium: a finished run's other modes drawn in the 3D view and
hidden by the visibility bar, the confidences in the legend and the Inspect tab, a mode chosen in the Label tab
taken as label, and the same posterior back from a saved session."""

from __future__ import annotations

import io
import re
import time

import numpy as np
import pytest
from headless import FRAME_PROBE_JS, canvas_png, chromium_path, served, workbench_page

from workbench.app.ui.run.modes import confidence_text, mode_label, mode_option

pytest.importorskip("playwright.sync_api")
from playwright.sync_api import expect  # noqa: E402

pytestmark = [pytest.mark.slow,  # needs Chromium, and the engine: pybullet and OpenGL
              pytest.mark.skipif(chromium_path() is None, reason="no system Chromium (Debian package `chromium`)")]

TIMEOUT_MS = 60_000
VIEWPORT = {"width": 1000, "height": 700}


@pytest.fixture(scope="module")
def workbench(tmp_path_factory, hidden_handle_dataset):
    from workbench.inference.config import EstimatorConfig

    # Three steps finish the run; the mug's hidden handle then leaves its heading open: several modes.
    with served(EstimatorConfig(particles=16, iterations=2), hidden_handle_dataset,
                sessions_dir=tmp_path_factory.mktemp("sessions")) as handle:
        yield handle


@pytest.fixture(scope="module")
def page(workbench):
    with workbench_page(workbench.url, TIMEOUT_MS, VIEWPORT, init_script=FRAME_PROBE_JS) as p:
        yield p


def canvas(page) -> np.ndarray:
    """The 3D view as drawn now: (H, W, 3) int16."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(canvas_png(page))).convert("RGB"), dtype=np.int16)


def settled_canvas(page, app, timeout_s: float = 30.0) -> np.ndarray:
    """The 3D view once it has gone quiet: two captures half a second apart that agree. Software WebGL on a loaded
    machine can take seconds to draw a change, so a fixed wait reads the frame before it (CI did)."""
    app.ui.call(app.display.throttle.flush)
    last = canvas(page)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        time.sleep(0.5)
        now = canvas(page)
        if changed_pixels(last, now) < 20:
            return now
        last = now
    return last


def changed_pixels(a: np.ndarray, b: np.ndarray) -> int:
    return int((np.abs(a - b).max(axis=2) > 30).sum())


def test_a_finished_run_shows_its_modes_and_confidences(page, workbench):
    app = workbench.app
    for i in range(3):
        page.get_by_role("button", name="Step").click()
        page.get_by_text(re.compile(rf"Iteration {i} of 2")).wait_for(timeout=TIMEOUT_MS)
    assert app.wait_for(lambda s: app.display.posterior is not None, 60)
    post = app.display.posterior
    several = [o for o in post.objects if len(o.modes) > 1]
    assert several

    # The legend names each object's confidence.
    page.get_by_text("Legend", exact=True).click()
    for o in post.objects:
        expect(page.locator(f'[data-confidence="{o.obj}"]')).to_have_text(f"({confidence_text(o)})",
                                                                            timeout=TIMEOUT_MS)
    page.get_by_text("Legend", exact=True).click()
    # The Inspect tab's table: each object's top probability and its other modes.
    page.get_by_role("tab", name="Inspect").click()
    page.get_by_text(re.compile(r"Posterior of the settled estimate · iteration 2")).wait_for(timeout=TIMEOUT_MS)
    for o in several:
        for m in o.modes[1:]:
            expect(page.get_by_role("cell", name=re.compile(re.escape(mode_label(o, m)))).first).to_be_visible(
                timeout=TIMEOUT_MS)
    page.get_by_role("tab", name="Estimator").click()

    # The ghosts and their labels are drawn: hiding them with the visibility bar changes the view, showing them
    # again brings it back. The observed points and the particles are hidden meanwhile: their squares and outlines
    # shimmer from one software-rendered frame to the next.
    for item in ("points", "particles", "truth"):
        page.get_by_role("button", name=f"● {item}").click()
        expect(page.get_by_role("button", name=f"○ {item}")).to_be_visible(timeout=TIMEOUT_MS)
    shown = settled_canvas(page, app)
    page.get_by_role("button", name="● modes").click()
    expect(page.get_by_role("button", name="○ modes")).to_be_visible(timeout=TIMEOUT_MS)
    hidden = settled_canvas(page, app)
    deadline = time.monotonic() + 30
    while changed_pixels(shown, hidden) <= 200 and time.monotonic() < deadline:
        hidden = settled_canvas(page, app)  # a quiet view can still be one drawn before the ghosts went
    page.get_by_role("button", name="○ modes").click()
    expect(page.get_by_role("button", name="● modes")).to_be_visible(timeout=TIMEOUT_MS)
    again = settled_canvas(page, app)
    deadline = time.monotonic() + 30
    while changed_pixels(hidden, again) <= 200 and time.monotonic() < deadline:
        again = settled_canvas(page, app)  # a quiet view can still be one drawn before the ghosts came back
    for item in ("points", "particles", "truth"):
        page.get_by_role("button", name=f"○ {item}").click()
        expect(page.get_by_role("button", name=f"● {item}")).to_be_visible(timeout=TIMEOUT_MS)
    assert changed_pixels(shown, hidden) > 200, changed_pixels(shown, hidden)
    # Shown again, they are drawn again (not pixel for pixel as before: the estimate's solids are re-sent with the
    # flush, and software WebGL shades them a little differently from one upload to the next).
    assert changed_pixels(hidden, again) > 200, changed_pixels(hidden, again)


def test_the_label_tab_takes_the_chosen_mode(page, workbench):
    app = workbench.app
    post = app.display.posterior
    o = next(o for o in post.objects if len(o.modes) > 1)
    name = app.display.names[o.obj]
    page.get_by_role("tab", name="Label").click()
    page.get_by_text("Modes to label with").wait_for(timeout=TIMEOUT_MS)
    # Choose mode 2 in the object's dropdown, as a user does: open it, click the option.
    dropdown = page.get_by_role("combobox", name=name, exact=True)
    expect(dropdown).to_have_value(mode_option(0, o, o.modes[0]), timeout=TIMEOUT_MS)
    dropdown.click()
    page.get_by_role("option", name=mode_option(1, o, o.modes[1])).click()
    assert app.wait_for(lambda s: app.labelling.modes.chosen()[0][o.obj] == 1, 30)
    page.get_by_role("button", name="Use best estimate as label").click()
    page.get_by_text(re.compile(rf"{re.escape(name)}: mode 2 \(p = {o.modes[1].probability:.2f}")).wait_for(
        timeout=TIMEOUT_MS)
    assert app.wait_for(lambda s: app.labelling.editor.labels[o.obj] is not None and np.array_equal(
        app.labelling.editor.labels[o.obj], o.modes[1].T), 30)
    page.get_by_role("tab", name="Estimator").click()


def test_a_saved_session_brings_the_same_modes_back(page, workbench):
    from headless import gui_input

    app = workbench.app
    texts = list(app.display.modes.texts)
    assert texts
    page.get_by_role("tab", name="Sessions").click()
    field = gui_input(page, "Session name")
    field.fill("modes")
    field.press("Enter")
    page.get_by_role("button", name="Save session").click()
    page.get_by_text(re.compile(r"Saved session modes")).wait_for(timeout=TIMEOUT_MS)

    page.get_by_role("tab", name="Estimator").click()
    page.get_by_role("button", name="Reset").click()
    assert app.wait_for(lambda s: s.iteration == -1 and s.last_state.reason == "reset", 60)
    page.get_by_role("tab", name="Inspect").click()
    page.get_by_text(re.compile(r"No posterior yet")).wait_for(timeout=TIMEOUT_MS)
    assert not app.display.modes.labels

    page.get_by_role("tab", name="Sessions").click()
    page.get_by_role("button", name="Load session").click()
    page.get_by_text(re.compile(r"Loaded session modes at iteration 2")).wait_for(timeout=TIMEOUT_MS)
    page.get_by_role("tab", name="Inspect").click()
    page.get_by_text(re.compile(r"Posterior of the settled estimate · iteration 2")).wait_for(timeout=TIMEOUT_MS)
    assert app.wait_for(lambda s: app.display.modes.texts == texts, 30), (app.display.modes.texts, texts)
    shown = texts[0].split(" · ", 1)[1]  # the table's cell is the ghost's label without its object's name
    expect(page.get_by_role("cell", name=re.compile(re.escape(shown))).first).to_be_visible(timeout=TIMEOUT_MS)
    page.get_by_role("tab", name="Estimator").click()
