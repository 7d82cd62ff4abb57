"""A whole sequence labelled once, in real headless Chromium (issue 68): a generated four-frame sequence's first
frame estimated, its estimate taken as the labels and checked on every frame (none flagged); one object's label
moved 3 cm and propagated to every frame (every frame flagged), then fitted to all frames (the flags clear); moved
again from a later frame on (that frame and the next flagged, the timeline marking them), the next flagged frame
shown and the label put back; saved, spoilt, and the saved labels read back (no flag, the Label tab showing
them). With WORKBENCH_LABEL_SCREENSHOT=PATH it also saves the folder with two flagged frames there (the README's
docs/label-sequence.png: ``WORKBENCH_LABEL_SCREENSHOT=docs/label-sequence.png pytest
tests/test_app_label_sequence_browser.py``)."""

from __future__ import annotations

import json
import os
import re

import numpy as np
import pytest
from headless import chromium_path, gui_input, served, workbench_page

pytest.importorskip("playwright.sync_api")
from playwright.sync_api import expect  # noqa: E402

pytestmark = [pytest.mark.slow,  # needs Chromium, and the engine: pybullet and OpenGL
              pytest.mark.skipif(chromium_path() is None, reason="no system Chromium (Debian package `chromium`)")]

TIMEOUT_MS = 60_000
VIEWPORT = {"width": 1000, "height": 900}
SCREENSHOT = os.environ.get("WORKBENCH_LABEL_SCREENSHOT")  # where to save the timeline's picture, if anywhere


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from workbench.synth.sequence import make_sequences

    out = tmp_path_factory.mktemp("label_seq")
    make_sequences(out, ["touching"], 1, 4, seed=0, width=320, height=240, arc_deg=6.0, sensor="kinect-like")
    return out


@pytest.fixture(scope="module")
def workbench(dataset):
    from workbench.inference.config import EstimatorConfig

    # Enough of a search to find both boxes of the first frame (16 particles and 2 iterations may leave one off).
    with served(EstimatorConfig(particles=32, iterations=4), dataset, 0, 0) as handle:
        yield handle


@pytest.fixture(scope="module")
def page(workbench):
    with workbench_page(workbench.url, TIMEOUT_MS, VIEWPORT) as p:
        yield p


def move_x(page, app, cm: float) -> np.ndarray:
    """The selected (first) object's label moved ``cm`` along the table's x in the pose fields -> the label sent."""
    editor = app.labelling.editor
    before = editor.labels[0].copy()
    x = gui_input(page, "x (cm)")
    # The field shows the label once the browser has the frame's labels (after a new frame, its place before them).
    # Waited for as long as any other step (a loaded machine takes seconds to show a new frame): typing into a field
    # that still shows the frame before would move the label from the wrong place.
    for _ in range(TIMEOUT_MS // 100):
        if abs(float(x.input_value()) - before[0, 3] * 100) < 0.01:
            break
        page.wait_for_timeout(100)
    else:
        raise AssertionError(f"the x field shows {x.input_value()}, not the label's {before[0, 3] * 100:.2f} cm")
    x.fill(f"{float(x.input_value()) + cm:.2f}")
    x.press("Enter")
    assert app.wait_for(lambda s: editor.labels[0] is not None
                        and abs(editor.labels[0][0, 3] - before[0, 3] - cm / 100) < 1e-3, 30), \
        (editor.labels[0][0, 3], before[0, 3], x.input_value(), app.state.failures[-1:])
    return editor.labels[0].copy()


def flags(app) -> list[int]:
    state = app.labelling.sequence.state
    return [f.im_id for f in state.frames if f.flagged] if state is not None and state.frames else []


def expect_flagged(page, app, frames: list[int]) -> None:
    """The summary, the engine's state and the timeline's buttons agree on the flagged ``frames``."""
    if frames:
        page.get_by_text(re.compile(rf"{len(frames)} flagged \({', '.join(map(str, frames))}\)")).wait_for(
            timeout=TIMEOUT_MS)
    else:
        page.get_by_text("no frame is flagged").wait_for(timeout=TIMEOUT_MS)
    assert flags(app) == frames
    for im in frames:
        expect(page.get_by_role("button", name=f"{im} ✗", exact=True)).to_be_visible(timeout=TIMEOUT_MS)


def press(page, name: str) -> None:
    """Click the Sequence labels folder's button ``name`` once the folder's buttons are back (the engine is done
    with the command before, ``SequenceLabelsPanel.act``)."""
    expect(page.get_by_role("button", name="Check every frame")).to_be_enabled(timeout=TIMEOUT_MS)
    page.get_by_role("button", name=name, exact="✓" in name).click()


def test_label_a_sequence_once(page, workbench, dataset):
    app = workbench.app
    page.get_by_role("button", name="Run").click()
    assert app.wait_for(lambda s: s.last_state is not None and s.last_state.reason in ("converged", "done"), 120), \
        app.state.failures

    page.get_by_role("tab", name="Label").click()
    page.get_by_role("button", name="Use best estimate as label").click()
    editor = app.labelling.editor
    assert app.wait_for(lambda s: all(T is not None for T in editor.labels), 60)
    start = [T.copy() for T in editor.labels]

    # Checked on every frame: the estimate agrees with each frame's depth.
    press(page, "Check every frame")
    expect_flagged(page, app, [])
    for im in range(4):
        expect(page.get_by_role("button", name=f"{im} ✓", exact=True)).to_be_visible(timeout=TIMEOUT_MS)

    # One label 3 cm off, propagated: every frame is flagged, and says why.
    move_x(page, app, 3.0)
    press(page, "to every frame")
    expect_flagged(page, app, [0, 1, 2, 3])
    expect(page.get_by_text(re.compile(r"\d+% \((seen past|behind something)\)")).first).to_be_visible(
        timeout=TIMEOUT_MS)

    # Fitted to all frames at once: back on the boxes, no flag.
    press(page, "Fit to all frames")
    page.get_by_text(re.compile(r"Fitted.* the still labels to frames 0, 1, 2, 3")).wait_for(timeout=TIMEOUT_MS)
    expect_flagged(page, app, [])
    assert app.wait_for(lambda s: np.linalg.norm(editor.labels[0][:3, 3] - start[0][:3, 3]) < 0.01, 30)

    # Frame 2 shown from the timeline (a frame the timeline had not processed), its label moved from there on.
    press(page, "2 ✓")
    assert app.wait_for(lambda s: s.view is not None and s.view.where[2] == 2, 60)
    assert app.wait_for(lambda s: all(T is not None for T in editor.labels), 30)
    move_x(page, app, 3.0)
    press(page, "from this frame on")
    expect_flagged(page, app, [2, 3])
    expect(page.get_by_role("button", name="0 ✓", exact=True)).to_be_visible(timeout=TIMEOUT_MS)
    # Seen past from frame 2 to the end, as a box taken out after frame 1 would be: ending its label is offered.
    expect(page.get_by_role("button", name=re.compile(r": last frame 1$"))).to_be_visible(timeout=TIMEOUT_MS)
    if SCREENSHOT:
        page.mouse.move(0, 0)  # no tooltip over the table
        page.wait_for_timeout(500)
        folder = page.locator(".mantine-Paper-root", has_text="Labelled frames").last
        folder.scroll_into_view_if_needed()
        box = folder.bounding_box()  # widened up to take in the folder's title, which sits above its box
        page.screenshot(path=SCREENSHOT, clip={"x": box["x"], "y": max(0.0, box["y"] - 14), "width": box["width"],
                                               "height": box["height"] + min(14.0, box["y"])})

    # Next flagged frame: frame 3; there the label put back, on every frame: no flag.
    press(page, "Next flagged frame")
    assert app.wait_for(lambda s: s.view is not None and s.view.where[2] == 3, 60)
    assert app.wait_for(lambda s: editor.labels[0] is not None, 30)
    move_x(page, app, -3.0)
    press(page, "to every frame")
    expect_flagged(page, app, [])

    # Saved beside the dataset's ground truth, which is left alone.
    scene = dataset / "test" / "000000"
    truth = (scene / "scene_gt.json").read_bytes()
    press(page, "Save sequence labels")
    page.get_by_text(re.compile(r"Saved sequence labels to .*scene_gt_labels\.json")).first.wait_for(
        timeout=TIMEOUT_MS)
    saved = json.loads((scene / "scene_gt_labels.json").read_text())
    assert sorted(saved, key=int) == ["0", "1", "2", "3"] and all(len(v) == 2 for v in saved.values())
    assert (scene / "scene_gt_info_labels.json").is_file() and (scene / "label_provenance.json").is_file()
    assert (scene / "scene_gt.json").read_bytes() == truth
    kept = editor.labels[0].copy()

    # Spoilt again, then the saved labels read back: no flag, the Label tab shows them.
    move_x(page, app, 3.0)
    press(page, "to every frame")
    expect_flagged(page, app, [0, 1, 2, 3])
    choose(page, "Start from", "saved labels")
    press(page, "Check every frame")
    page.get_by_text(re.compile(r"Read the labels saved in .*scene_gt_labels\.json for 4 frames")).wait_for(
        timeout=TIMEOUT_MS)
    expect_flagged(page, app, [])
    assert app.wait_for(lambda s: np.allclose(editor.labels[0], kept, atol=1e-5), 30)
    assert not app.state.display_errors


def choose(page, label: str, option: str) -> None:
    """Pick ``option`` in the viser dropdown labelled ``label`` (a Mantine select: open it, click the option)."""
    page.get_by_role("combobox", name=label, exact=True).click()
    page.get_by_role("option", name=option, exact=True).click()
