"""Sequences in the workbench in real headless Chromium: a generated three-frame sequence loaded,
its first frame stepped to the end, Next frame twice, the timeline listing the three frames with their statuses, a
jump back showing that frame's own estimate, the plots across frames drawn, and a saved session bringing the
position back, from where Next goes on."""

from __future__ import annotations

import re

import numpy as np
import pytest
from headless import chromium_path, color_extent, gui_input, served, workbench_page

pytest.importorskip("playwright.sync_api")
from playwright.sync_api import expect  # noqa: E402

from workbench.track.config import TrackConfig  # noqa: E402

pytestmark = [pytest.mark.slow,  # needs Chromium, and the engine: pybullet and OpenGL
              pytest.mark.skipif(chromium_path() is None, reason="no system Chromium (Debian package `chromium`)")]

TIMEOUT_MS = 60_000
# A tracked frame's own short budget of iterations, which the status line counts against.
TRACKED = TrackConfig().iterations
VIEWPORT = {"width": 1000, "height": 700}
FIRST_OBJECT = (66, 135, 245)  # colors.OBJECT_COLORS[0]: the first object's line in the plots across frames


@pytest.fixture(scope="module")
def workbench(tmp_path_factory):
    from workbench.inference.config import EstimatorConfig
    from workbench.synth.sequence import make_sequences

    # As `workbench make-scenes OUT --categories touching --sequence 3 --arc 5`, at 320x240 to stay quick.
    data = tmp_path_factory.mktemp("seq")
    make_sequences(data, ["touching"], 1, 3, seed=0, width=320, height=240, arc_deg=5.0, sensor="kinect-like")
    with served(EstimatorConfig(particles=16, iterations=2), data, 0, 0,
                sessions_dir=tmp_path_factory.mktemp("sessions")) as handle:
        yield handle


@pytest.fixture(scope="module")
def page(workbench):
    with workbench_page(workbench.url, TIMEOUT_MS, VIEWPORT) as p:
        yield p


def frame_row(im_id: int, status: str, on_show: bool = False) -> re.Pattern:
    """The timeline table's row of a frame, as the browser reads it (cells separated by white space)."""
    return re.compile(rf"^\s*{'▶' if on_show else ''}\s*{im_id}\s*{re.escape(status)}")


def expect_on_show(page, app, im_id: int) -> None:
    page.get_by_text(re.compile(rf"frame {im_id} on show")).wait_for(timeout=TIMEOUT_MS)
    assert app.wait_for(lambda s: s.view is not None and s.view.where[2] == im_id and s.cloud is not None, 60)
    expect(page.get_by_text(re.compile(rf"scene 0 · frame {im_id}$")).first).to_be_visible(timeout=TIMEOUT_MS)


def test_next_frame_twice_jump_back_and_plots_across_frames(page, workbench):
    app = workbench.app
    for i in range(3):  # the first frame's run to its end (a budget of 2 iterations)
        page.get_by_role("button", name="Step").click()
        page.get_by_text(re.compile(rf"Iteration {i} of 2")).wait_for(timeout=TIMEOUT_MS)
    page.get_by_role("tab", name="Data").click()
    page.get_by_text(re.compile(r"Scene 0, frames 0–2: frame 0 on show")).wait_for(timeout=TIMEOUT_MS)

    shown = {}
    for im_id in (1, 2):
        page.get_by_role("button", name="Next frame").click()
        expect_on_show(page, app, im_id)
        page.get_by_text(re.compile(rf"Frame {im_id}: tracked in [\d.]+ s, camera motion given")).wait_for(
            timeout=TIMEOUT_MS)
        assert app.wait_for(lambda s: app.display.posterior is not None, 60)
        shown[im_id] = (app.state.cloud.poses.copy(), app.display.posterior)
    # The status line counts a tracked frame's iterations against its own short budget.
    expect(page.get_by_text(re.compile(rf"Iteration {TRACKED} of {TRACKED}\b"))).to_be_visible(timeout=TIMEOUT_MS)

    # The timeline: three frames with their statuses, the last on show and no frame after it.
    for im_id in (0, 1, 2):
        expect(page.get_by_role("button", name=str(im_id), exact=True)).to_be_visible(timeout=TIMEOUT_MS)
    rows = page.locator("tr")
    expect(rows.filter(has_text=frame_row(0, "estimated"))).to_have_count(1, timeout=TIMEOUT_MS)
    expect(rows.filter(has_text=frame_row(1, "tracked"))).to_have_count(1, timeout=TIMEOUT_MS)
    expect(rows.filter(has_text=frame_row(2, "tracked", on_show=True))).to_have_count(1, timeout=TIMEOUT_MS)
    expect(page.get_by_text("It is the scene's last frame")).to_be_visible(timeout=TIMEOUT_MS)
    expect(page.get_by_role("button", name="Next frame")).to_be_disabled(timeout=TIMEOUT_MS)

    # The plots across frames: each object's position and confidence over the three frames.
    for title in ("position x (cm, table frame)", "height z (cm above the table)",
                  "confidence (top mode's probability)"):
        expect(page.get_by_text(title)).to_be_visible(timeout=TIMEOUT_MS)
    drawn = app.sequence.tab.plots.drawn
    assert set(drawn) == {"x", "y", "z", "p"} and all(len(plot.data[0]) == 3 for _, plot in drawn.values())
    chart = page.locator(".uplot:visible").first  # position x: the first object's line across the chart
    assert app.wait_for(lambda s: color_extent(chart.screenshot(), FIRST_OBJECT)[1] > 0.5, 60), \
        color_extent(chart.screenshot(), FIRST_OBJECT)

    # Back to frame 1: its own estimate and posterior, as they were shown after its Next (nothing re-run).
    page.get_by_role("button", name="1", exact=True).click()
    expect_on_show(page, app, 1)
    poses, posterior = shown[1]
    assert app.wait_for(lambda s: s.cloud.poses.shape == poses.shape and np.array_equal(s.cloud.poses, poses), 60)
    assert app.wait_for(lambda s: app.display.posterior is not None, 60)
    assert [o.confidence for o in app.display.posterior.objects] == [o.confidence for o in posterior.objects]
    expect(page.get_by_role("button", name="Next frame")).to_be_enabled(timeout=TIMEOUT_MS)


def test_a_session_saves_and_restores_the_sequence_position(page, workbench):
    app = workbench.app
    page.get_by_role("tab", name="Sessions").click()
    name = gui_input(page, "Session name")
    name.fill("seq")
    name.press("Enter")
    page.get_by_role("button", name="Save session").click()
    page.get_by_text(re.compile(r"Saved session seq \(frame 1 of a sequence of 3")).wait_for(timeout=TIMEOUT_MS)

    # Elsewhere in the sequence (frame 2, as it was), then the session back.
    page.get_by_role("tab", name="Data").click()
    page.get_by_role("button", name="Next frame").click()
    expect_on_show(page, app, 2)
    page.get_by_role("tab", name="Sessions").click()
    page.get_by_role("button", name="Load session").click()
    page.get_by_text("The current run is not saved").wait_for(timeout=TIMEOUT_MS)
    page.get_by_role("button", name="Load anyway").click()
    page.get_by_text(re.compile(rf"Loaded session seq at iteration {TRACKED}\b")).wait_for(timeout=TIMEOUT_MS)

    page.get_by_role("tab", name="Data").click()
    expect_on_show(page, app, 1)
    rows = page.locator("tr")
    expect(rows.filter(has_text=frame_row(0, "estimated · run not in the session"))).to_have_count(
        1, timeout=TIMEOUT_MS)
    expect(rows.filter(has_text=frame_row(1, "tracked", on_show=True))).to_have_count(1, timeout=TIMEOUT_MS)
    expect(rows.filter(has_text=frame_row(2, "tracked · run not in the session"))).to_have_count(
        1, timeout=TIMEOUT_MS)
    assert app.config.particles == 16  # the panel keeps the sequence's settings, not the tracked frame's
    expect(page.get_by_text(re.compile(rf"Iteration {TRACKED} of {TRACKED}\b"))).to_be_visible(timeout=TIMEOUT_MS)

    # A frame whose run the session does not hold: a message beside the timeline, frame 1 stays.
    page.get_by_role("button", name="0", exact=True).click()
    expect(page.locator("strong", has_text="frame 0's run is not in the loaded session")).to_be_visible(
        timeout=TIMEOUT_MS)  # beside the timeline (the banner and a notification say it too)
    assert app.state.view.where[2] == 1
    # Next goes on tracking from the restored frame.
    page.get_by_role("button", name="Next frame").click()
    expect_on_show(page, app, 2)
    page.get_by_text(re.compile(r"Frame 2: tracked in [\d.]+ s")).wait_for(timeout=TIMEOUT_MS)
