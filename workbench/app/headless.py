"""Driving the workbench from headless Chromium, for the browser tests and ``scripts/screenshot.py``.

Playwright's Python package drives the system's Chromium (never ``playwright install``); SwiftShader renders
viser's WebGL without a GPU. Pixel checks read PNG bytes with Pillow.
"""

from __future__ import annotations

import io
import os
import shutil
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


def open_workbench(browser, url: str, timeout_ms: float = 60_000, viewport: dict | None = None):
    """A new page on ``url``, once the panel is up; viser's "software WebGL" notice is closed so that it does not
    cover the view. A smaller ``viewport`` makes software WebGL cheaper."""
    page = browser.new_page(viewport=viewport or VIEWPORT)
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
