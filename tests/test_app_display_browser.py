"""The workbench read at a glance, in real headless Chromium, on a small dataset of its own: the demo's
frame with a colour image (rgb/) and the demo's ground truth. The colour image is shown; the truth table gives each
object's confidence once the run has a posterior ("–" before); the run's buttons share one row, so the tabs start
high; the plots resize and pop out into a window of their own and come back."""

from __future__ import annotations

import io
import re
import shutil

import numpy as np
import pytest
from headless import chromium_path, served, workbench_page

from workbench.app.ui.run.modes import chance

pytest.importorskip("playwright.sync_api")
from playwright.sync_api import expect  # noqa: E402

pytestmark = [pytest.mark.slow,  # needs Chromium, and the engine: pybullet and OpenGL
              pytest.mark.skipif(chromium_path() is None, reason="no system Chromium (Debian package `chromium`)")]

TIMEOUT_MS = 60_000
VIEWPORT = {"width": 1000, "height": 700}
ITERATIONS = 2  # the budget: the third Step finishes the run, which then has a posterior
RED, BLUE = (220, 30, 40), (30, 60, 220)  # the colour image: red left half, blue right half


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """The bundled demo (one frame, two boxes, scene_gt.json) with a colour image in rgb/, as a copy."""
    from PIL import Image

    from workbench.app.engine.engine import DEMO_DIR

    out = tmp_path_factory.mktemp("rgb_dataset") / "demo_rgb"
    shutil.copytree(DEMO_DIR, out)
    scene = out / "test" / "000000"
    depth = next((scene / "depth").iterdir())
    width, height = Image.open(depth).size
    rgb = np.zeros((height, width, 3), np.uint8)
    rgb[:, : width // 2], rgb[:, width // 2:] = RED, BLUE
    (scene / "rgb").mkdir()
    Image.fromarray(rgb).save(scene / "rgb" / depth.name)
    return out


@pytest.fixture(scope="module")
def workbench(dataset, tmp_path_factory):
    from workbench.inference.config import EstimatorConfig

    with served(EstimatorConfig(particles=16, iterations=ITERATIONS), dataset, 0, 0,
                sessions_dir=tmp_path_factory.mktemp("sessions")) as handle:
        yield handle


@pytest.fixture(scope="module")
def page(workbench):
    with workbench_page(workbench.url, TIMEOUT_MS, VIEWPORT) as p:
        yield p


def step(page, app) -> int:
    nxt = app.state.iteration + 1
    page.get_by_role("button", name="Step").click()
    page.get_by_text(re.compile(rf"Iteration {nxt}\b")).first.wait_for(timeout=TIMEOUT_MS)
    return nxt


def visible(locator):
    """The first visible element of ``locator`` (the same control may be in a hidden tab, or in two places)."""
    return locator.locator("visible=true").first


COLOUR_IMAGE = "xpath=//*[normalize-space(text())='colour image']/following-sibling::*//img"


def share_of(png: bytes, rgb: tuple[int, int, int], tolerance: int = 40) -> float:
    """The share of the image's pixels within ``tolerance`` of ``rgb``."""
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)
    return float((np.abs(img - np.array(rgb)).max(axis=2) <= tolerance).mean())


def test_the_colour_image_is_shown(page, workbench):
    assert workbench.app.state.view.rgb_image is not None
    page.get_by_role("tab", name="Data").click()
    image = visible(page.locator(COLOUR_IMAGE))
    expect(image).to_be_visible(timeout=TIMEOUT_MS)
    png = image.screenshot()
    assert share_of(png, RED) > 0.3 and share_of(png, BLUE) > 0.3, (share_of(png, RED), share_of(png, BLUE))
    page.get_by_role("tab", name="Label").click()
    image = visible(page.locator(COLOUR_IMAGE))
    expect(image).to_be_visible(timeout=TIMEOUT_MS)
    png = image.screenshot()
    assert share_of(png, RED) > 0.3 and share_of(png, BLUE) > 0.3
    page.get_by_role("tab", name="Estimator").click()


def test_the_run_buttons_share_one_row_and_the_tabs_start_high(page, workbench):
    boxes = [page.get_by_role("button", name=n, exact=True).bounding_box() for n in ("Step", "Run", "Pause", "Reset")]
    assert len({round(b["y"]) for b in boxes}) == 1, boxes
    assert all(a["x"] + a["width"] <= b["x"] for a, b in zip(boxes, boxes[1:])), boxes
    # With the status, the View box and the truth table above them, the tabs still start in the top half of a
    # 1000-px-high window (the panel's width, and so its layout, does not depend on the window's).
    step(page, workbench.app)
    page.get_by_text("Estimate vs ground truth").wait_for(timeout=TIMEOUT_MS)
    tabs = page.get_by_role("tab", name="Estimator").bounding_box()
    assert tabs["y"] < 480, tabs


def test_the_truth_table_shows_each_objects_confidence_once_the_run_has_a_posterior(page, workbench):
    app = workbench.app
    while app.state.iteration < ITERATIONS - 1:
        step(page, app)
    assert app.wait_for(lambda s: s.truth is not None and s.truth.iteration == s.iteration, 60)
    assert app.display.posterior is None and all(np.isnan(r["confidence"]) for r in app.state.truth.rows)
    expect(page.get_by_role("cell", name="–", exact=True)).to_have_count(len(app.state.truth.rows),
                                                                        timeout=TIMEOUT_MS)
    step(page, app)  # the budget reached: the run is settled, with its posterior
    assert app.wait_for(lambda s: s.truth is not None and s.truth.iteration == ITERATIONS
                        and app.display.posterior is not None, 120)
    posterior, truth = app.display.posterior, app.state.truth
    # The table scores the settled answer, the estimate drawn, and gives each object's top mode's probability, of
    # all its chances (elsewhere included, as every probability the panel shows).
    settled = np.stack([o.modes[0].T for o in posterior.objects])
    assert np.allclose(truth.estimate, settled)
    confidence = {o.obj: chance(o, o.modes[0]) for o in posterior.objects}
    for row in truth.rows:
        assert row["confidence"] == pytest.approx(confidence[row["index"]])
        page.get_by_role("cell", name=f"{row['confidence']:.2f}", exact=True).first.wait_for(timeout=TIMEOUT_MS)
    expect(page.get_by_role("cell", name="–", exact=True)).to_have_count(0, timeout=TIMEOUT_MS)


def chart_boxes(page) -> list[dict]:
    charts = page.locator(".uplot")
    return [charts.nth(i).bounding_box() for i in range(charts.count())]


def test_the_plot_height_control_resizes_the_charts(page, workbench):
    app = workbench.app
    if app.state.iteration < 0:
        step(page, app)
    page.get_by_role("tab", name="Plots").click()
    page.locator(".uplot").first.wait_for(timeout=TIMEOUT_MS)
    app.plots.size.value = 300  # as another tab would set it
    expect(page.locator(".uplot").first).to_have_js_property("offsetHeight", 300, timeout=TIMEOUT_MS)
    app.plots.size.value = 140
    expect(page.locator(".uplot").first).to_have_js_property("offsetHeight", 140, timeout=TIMEOUT_MS)


def test_the_plots_pop_out_into_a_window_and_come_back(page, workbench):
    app = workbench.app
    if app.state.iteration < 0:
        step(page, app)
    page.get_by_role("tab", name="Plots").click()
    page.locator(".uplot").first.wait_for(timeout=TIMEOUT_MS)
    docked = chart_boxes(page)
    page.get_by_role("button", name="Pop out").click()
    page.get_by_text("The charts are in their own window.").wait_for(timeout=TIMEOUT_MS)
    expect(page.locator(".uplot").first).to_have_js_property("offsetHeight", 220, timeout=TIMEOUT_MS)
    wide = 1.3 * max(b["width"] for b in docked)
    page.wait_for_function(  # uPlot takes its width from its container once laid out
        "w => [...document.querySelectorAll('.uplot')].every(e => e.offsetWidth > w)", arg=wide, timeout=TIMEOUT_MS)
    popped = chart_boxes(page)
    assert len(popped) == len(docked)
    assert min(b["width"] for b in popped) > wide, (popped, docked)
    # The window leaves the panel free (from a window 1000 px wide), and a new iteration reaches its charts.
    window = page.locator("[data-floating-window]", has=page.locator(".uplot")).bounding_box()
    assert window["x"] + window["width"] <= page.get_by_role("button", name="Step").bounding_box()["x"], window
    step(page, app)
    assert len(chart_boxes(page)) == len(docked) and app.plots.drawn
    visible(page.get_by_role("button", name="Put back")).click()
    expect(page.get_by_role("button", name="Pop out")).to_be_visible(timeout=TIMEOUT_MS)
    expect(page.locator(".uplot").first).to_have_js_property("offsetHeight", 140, timeout=TIMEOUT_MS)
    page.wait_for_function(
        "w => [...document.querySelectorAll('.uplot')].every(e => Math.abs(e.getBoundingClientRect().width - w) < 1)",
        arg=docked[0]["width"], timeout=TIMEOUT_MS)
    back = chart_boxes(page)
    assert [round(b["width"]) for b in back] == [round(b["width"]) for b in docked], (back, docked)
    page.get_by_role("tab", name="Estimator").click()
