"""Driving the workbench from headless Chromium, for the browser tests and ``scripts/screenshot.py``.

Playwright's Python package drives the system's Chromium (never ``playwright install``); SwiftShader renders
viser's WebGL without a GPU. Pixel checks read PNG bytes with Pillow.
"""

from __future__ import annotations

import io
import os
import shutil
import socket
import threading
import time
from contextlib import contextmanager
from typing import Iterator

import numpy as np

CHROMIUM_ARGS = [
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--no-sandbox",
    "--disable-background-networking",
    "--disable-dev-shm-usage",
    "--mute-audio",
]
VIEWPORT = {"width": 1280, "height": 800}


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now, for a workbench served to a headless browser (tests, screenshots)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def chromium_path() -> str | None:
    """The system Chromium: ``WORKBENCH_CHROMIUM``, else /usr/bin/chromium or whatever ``chromium`` is on PATH."""
    for candidate in (os.environ.get("WORKBENCH_CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium"),
                      shutil.which("chromium-browser")):
        if candidate and os.path.exists(candidate):
            return candidate
    return None


@contextmanager
def chromium() -> Iterator[object]:
    """A headless Chromium ``Browser`` (closed on exit)."""
    from playwright.sync_api import sync_playwright

    path = chromium_path()
    if path is None:
        raise RuntimeError("no Chromium found: install Debian's `chromium` or set WORKBENCH_CHROMIUM")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=path, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


@contextmanager
def served(config, *frame, **serve_args) -> Iterator[object]:
    """``app.ui.server.serve(*frame, **serve_args)`` with ``config`` (an EstimatorConfig) on a free port, not
    blocking, with one evaluation worker (the machine running the tests also runs Chromium's software WebGL) -> its
    handle once the frame loaded, stopped on exit. A frame that fails to load fails the test, and so does a display
    error while it served."""
    from workbench.app.ui.server import serve

    handle = serve(*frame, block=False, port=free_port(), workers=1, config=config, **serve_args)
    try:
        assert handle.app.wait_for(lambda s: s.view is not None or s.failures, 180), "the frame did not load"
        assert handle.app.state.view is not None, handle.app.state.failures
        yield handle
        assert not handle.app.state.display_errors
    finally:
        handle.stop()


@contextmanager
def workbench_page(url: str, timeout_ms: float, viewport: dict, init_script: str | None = None) -> Iterator[object]:
    """A page of the workbench at ``url`` in a Chromium of its own (``open_workbench``), closed on exit."""
    with chromium() as browser:
        page = open_workbench(browser, url, timeout_ms, viewport, init_script=init_script)
        yield page
        page.close()


def open_workbench(browser, url: str, timeout_ms: float = 60_000, viewport: dict | None = None,
                   init_script: str | None = None):
    """A new page on ``url``, once the panel is up; viser's "software WebGL" notice is closed so that it does not
    cover the view. A smaller ``viewport`` makes software WebGL cheaper; ``init_script`` (e.g. ``FRAME_PROBE_JS``)
    runs in the page before its own scripts."""
    page = browser.new_page(viewport=viewport or VIEWPORT)
    if init_script:
        page.add_init_script(init_script)
    page.goto(url)
    page.get_by_role("button", name="Step").wait_for(timeout=timeout_ms)
    dismiss_notifications(page)
    return page


def dismiss_notifications(page, wait_ms: float = 0) -> None:
    """Close every notification on the page (best effort: they are cosmetic). ``wait_ms``: first wait that long
    for one to appear (viser's software-WebGL notice comes a few seconds after the page)."""
    if wait_ms:
        try:
            page.locator(".mantine-Notification-root").first.wait_for(timeout=wait_ms)
        except Exception:  # none came
            return
    closers = page.locator(".mantine-Notification-root button")
    for i in range(closers.count()):
        try:
            # force: skip the "stable for two frames" wait, slow under software rendering.
            closers.nth(i).click(timeout=2000, force=True)
        except Exception:  # it may have closed itself meanwhile
            pass


def canvas_png(page) -> bytes:
    """A screenshot of the 3D view only (the WebGL canvas), as PNG bytes."""
    return page.locator("canvas").first.screenshot()


def image_stats(png: bytes) -> tuple[float, float]:
    """-> (standard deviation of the grey levels, fraction of pixels that differ from the most common colour).
    A blank canvas gives (0, 0); a drawn scene a few tenths of non-background pixels."""
    from PIL import Image

    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)
    flat = rgb.reshape(-1, 3)
    colours, counts = np.unique(flat, axis=0, return_counts=True)
    background = colours[np.argmax(counts)]
    differs = np.abs(flat - background).max(axis=1) > 24
    return float(rgb.mean(axis=2).std()), float(differs.mean())


def gui_input(page, label: str):
    """The input of the viser GUI row labelled ``label`` (text inputs are not tied to their label by id)."""
    return page.locator(
        f"xpath=//label[normalize-space(text())='{label}']/ancestor::div[contains(@class,'mantine-Flex-root')][1]//input"
    ).first


def color_extent(png: bytes, rgb: tuple[int, int, int], tolerance: int = 40) -> tuple[int, float]:
    """-> (how many pixels are within ``tolerance`` of ``rgb``, the share of the image's width they span). A
    chart's line in that colour spans most of the width; a blank or stale chart has none of it."""
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)
    hit = np.abs(img - np.array(rgb, dtype=np.int16)).max(axis=2) <= tolerance
    cols = np.nonzero(hit.any(axis=0))[0]
    span = (cols[-1] - cols[0] + 1) / img.shape[1] if cols.size else 0.0
    return int(hit.sum()), float(span)


# Counts, in the page, the animation frames in which WebGL drew anything (three.js clears and draws inside
# requestAnimationFrame callbacks) and every requestAnimationFrame callback (any script animating). Added with
# ``page.add_init_script`` before the page loads; read with ``frame_counts``.
FRAME_PROBE_JS = """
(() => {
  const s = {frames: 0, draws: 0, callbacks: 0, stamp: 0, counted: -1};
  window.__workbenchFrames = s;
  const raf = window.requestAnimationFrame.bind(window);
  window.requestAnimationFrame = (cb) => raf((t) => { s.callbacks++; s.stamp = t; return cb(t); });
  const names = ["clear", "drawArrays", "drawElements", "drawArraysInstanced", "drawElementsInstanced",
                 "drawRangeElements"];
  for (const C of [window.WebGL2RenderingContext, window.WebGLRenderingContext]) {
    if (!C) continue;
    for (const name of names) {
      const original = C.prototype[name];
      if (!original) continue;
      C.prototype[name] = function (...args) {
        s.draws++;
        if (s.counted !== s.stamp) { s.frames++; s.counted = s.stamp; }
        return original.apply(this, args);
      };
    }
  }
})();
"""


def frame_counts(page) -> dict[str, int]:
    """Totals since the page loaded (needs ``FRAME_PROBE_JS``): ``frames`` (animation frames with WebGL drawing),
    ``draws`` (WebGL clear and draw calls), ``callbacks`` (requestAnimationFrame callbacks of any script),
    ``animations`` (CSS/Web animations running now)."""
    return page.evaluate(
        "() => ({...window.__workbenchFrames, "
        "animations: document.getAnimations().filter(a => a.playState === 'running').length})"
    )


# Server -> browser messages that change only the panel: viser's client applies them without drawing the 3D view
# (client/src/messageQueue.ts); every other message makes it draw frames for 250 ms.
GUI_ONLY_MESSAGES = {
    "GuiUpdateMessage", "GuiRemoveMessage", "GuiModalMessage", "GuiCloseModalMessage", "GuiPanelMessage",
    "GuiPanelRemoveMessage", "GuiSetPanelCollapsedMessage", "GuiSetPanelHeightMessage",
    "GuiSetPanelPositionMessage", "GuiSetPanelWidthMessage", "SetGuiPanelLabelMessage", "NotificationShowMessage",
    "NotificationUpdateMessage", "RemoveNotificationMessage",
}


def is_scene_message(message) -> bool:
    """Whether a viser message makes the browser draw the 3D view (anything but a panel-only message)."""
    from viser._messages import _CreateGuiComponentMessage

    return not isinstance(message, _CreateGuiComponentMessage) and type(message).__name__ not in GUI_ONLY_MESSAGES


class SentMessages:
    """Every message viser puts on a websocket while ``record()`` is active (for every connected tab), as
    (monotonic time s, type name, makes the 3D view draw). Counted as serialised for sending, so after viser dropped
    the superseded ones."""

    def __init__(self) -> None:
        self.log: list[tuple[float, str, bool]] = []
        self._lock = threading.Lock()

    @contextmanager
    def record(self) -> Iterator["SentMessages"]:
        from viser.infra._messages import Message

        original = Message.as_serializable_dict

        def counted(message, *args, **kwargs):
            with self._lock:
                self.log.append((time.monotonic(), type(message).__name__, is_scene_message(message)))
            return original(message, *args, **kwargs)

        Message.as_serializable_dict = counted
        try:
            yield self
        finally:
            Message.as_serializable_dict = original

    def scene_since(self, t0: float, t1: float | None = None) -> list[str]:
        """Type names of the scene messages sent between monotonic times ``t0`` and ``t1`` (default: now)."""
        t1 = time.monotonic() if t1 is None else t1
        with self._lock:
            return [name for t, name, scene in self.log if scene and t0 <= t < t1]

    def redraws(self, t0: float, t1: float | None = None, gap: float = 0.1) -> list[float]:
        """Start times (monotonic s) of the bursts of scene messages sent between ``t0`` and ``t1`` (default: now),
        a burst being messages no more than ``gap`` s apart: one redraw of the 3D view each."""
        t1 = time.monotonic() if t1 is None else t1
        with self._lock:
            times = [t for t, _, scene in self.log if scene and t0 <= t < t1]
        return [t for i, t in enumerate(times) if i == 0 or t - times[i - 1] > gap]
