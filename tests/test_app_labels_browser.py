"""Labels into a dataset's own ground truth in real headless Chromium: one object labelled and saved over
scene_gt.json (its entry replaced, every other kept), the truth table and the drawn truth following the file, then
the backup listed and restored after confirming, and a damaged backup refused with a message naming it."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
from headless import chromium_path, gui_input, served, workbench_page

pytest.importorskip("playwright.sync_api")
from playwright.sync_api import expect  # noqa: E402

pytestmark = [pytest.mark.slow,  # needs Chromium, and the engine: pybullet and OpenGL
              pytest.mark.skipif(chromium_path() is None, reason="no system Chromium (Debian package `chromium`)")]

TIMEOUT_MS = 60_000
VIEWPORT = {"width": 1000, "height": 700}


@pytest.fixture(scope="module")
def dataset(touching_dataset, tmp_path_factory):
    """A private copy of a generated frame of two touching boxes (320x240): its scene_gt.json is written."""
    out = tmp_path_factory.mktemp("labels_browser") / "dataset"
    shutil.copytree(touching_dataset, out)
    return out


@pytest.fixture(scope="module")
def workbench(dataset):
    from workbench.inference.config import EstimatorConfig

    with served(EstimatorConfig(particles=16, iterations=2), dataset, 0, 0) as handle:
        yield handle


@pytest.fixture(scope="module")
def page(workbench):
    with workbench_page(workbench.url, TIMEOUT_MS, VIEWPORT) as p:
        yield p


def scores(rows: list[dict]) -> list[tuple]:
    """The truth table's errors (its confidences are NaN before the run ends, and NaN equals nothing)."""
    return [(r["index"], r["position_cm"], r["rotation_deg"], r["add_s_mm"]) for r in rows]


def test_one_label_over_scene_gt_then_the_backup_restored(page, workbench, dataset):
    app = workbench.app
    scene_gt = dataset / "test" / "000000" / "scene_gt.json"
    original = scene_gt.read_bytes()
    entries = json.loads(original)["0"]
    page.get_by_role("button", name="Step").click()
    assert app.wait_for(lambda s: s.truth is not None and s.iteration == 0, 60), app.state.failures
    truth_before, drawn_before = app.state.truth, app.display.view.gt_T_world_obj.copy()

    # Label the first object only: its best estimate, 1 cm further along x.
    page.get_by_role("tab", name="Label").click()
    x = gui_input(page, "x (cm)")
    x.fill(f"{float(x.input_value()) + 1.0:.2f}")
    x.press("Enter")
    editor = app.labelling.editor
    assert app.wait_for(lambda s: editor.labels[0] is not None and editor.labels[1] is None, 30)
    label = editor.labels[0].copy()
    page.get_by_label("Overwrite scene_gt.json").check()
    page.get_by_role("button", name="Save labels").click()
    page.get_by_text(re.compile(r"Saved labels to .*scene_gt\.json · the original was kept")).first.wait_for(
        timeout=TIMEOUT_MS)
    saved = json.loads(scene_gt.read_text())["0"]
    assert len(saved) == len(entries) and saved[1:] == entries[1:] and saved[0] != entries[0]

    # The truth table and the drawn truth follow the file: the first object's truth is now the label.
    assert app.wait_for(lambda s: s.truth is not truth_before, 60)
    assert np.allclose(app.display.view.gt_T_world_obj[0], label, atol=1e-6)
    assert np.allclose(app.display.view.gt_T_world_obj[1], drawn_before[1], atol=1e-9)
    rows, old = scores(app.state.truth.rows), scores(truth_before.rows)
    assert rows[1] == old[1] and rows[0][1] != pytest.approx(old[0][1])

    # The backup, listed and restored only after confirming: the original bytes are back.
    page.get_by_role("button", name="List backups").click()
    page.get_by_text(re.compile(r"1 backup\(s\) of .*scene_gt\.json")).first.wait_for(timeout=TIMEOUT_MS)
    page.get_by_role("button", name="Restore backup").click()
    page.get_by_text(re.compile(r"Restore scene_gt\.json\.bak-\d+")).first.wait_for(timeout=TIMEOUT_MS)
    assert scene_gt.read_text() != original.decode()  # nothing happens before the confirmation
    page.get_by_role("button", name="Confirm restore").click()
    page.get_by_text(re.compile(r"Restored .*scene_gt\.json · restored from")).first.wait_for(timeout=TIMEOUT_MS)
    assert scene_gt.read_bytes() == original
    assert app.wait_for(lambda s: np.allclose(app.display.view.gt_T_world_obj, drawn_before, atol=1e-9), 60)
    assert app.wait_for(lambda s: scores(s.truth.rows) == old, 60)

    # A damaged backup (the newest, so the one chosen): a message naming it, scene_gt.json untouched.
    damaged = scene_gt.with_name("scene_gt.json.bak-29991231T235959000000")
    damaged.write_text('{"0": [')
    page.get_by_role("button", name="List backups").click()
    page.get_by_text(re.compile(r"3 backup\(s\)")).first.wait_for(timeout=TIMEOUT_MS)
    page.get_by_role("button", name="Restore backup").click()
    page.get_by_role("button", name="Confirm restore").click()
    expect(page.get_by_text(re.compile(rf"{re.escape(str(damaged))}.*corrupt JSON")).first).to_be_visible(
        timeout=TIMEOUT_MS)
    assert scene_gt.read_bytes() == original
    page.get_by_role("button", name="Step").click()  # the server and the run go on
    assert app.wait_for(lambda s: s.iteration == 1, 60), app.state.failures
