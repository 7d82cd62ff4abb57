"""Save the README screenshots, in headless Chromium on the demo frame:

- docs/screenshot.png: mid-run, the Plots tab beside the 3D view with its legend;
- docs/inspect.png: the Inspect tab, one particle before (wireframe) and after physics, and how physics moved it.

    python scripts/screenshot.py [--out docs/screenshot.png] [--inspect-out docs/inspect.png] [--particles 128]
                                 [--iterations 15] [--rank 5]

With ``--dataset DIR --scene ID --frame ID`` (e.g. ../shared/datasets/ycbv-real-dev --scene 1 --frame 1), one
picture of that frame after ``--iterations``, seen from the sensor: the estimate (solid), the observed points
(grey), the ground truth (black outlines) and the table of errors against it, into ``--out``
(docs/ycbv.png in the README).
"""

from __future__ import annotations

import argparse
import socket
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from workbench.app import protocol as p  # noqa: E402
from workbench.app.headless import chromium, dismiss_notifications, image_stats, open_workbench  # noqa: E402
from workbench.app.server import serve  # noqa: E402
from workbench.inference.config import EstimatorConfig  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def save(page, out: Path, app) -> bool:
    """Screenshot the page into ``out`` unless the 3D view looks blank."""
    time.sleep(2.0)  # let SwiftShader catch up with the last updates
    dismiss_notifications(page, wait_ms=3_000)
    png = page.screenshot()
    std, drawn = image_stats(png)
    if drawn < 0.05:
        print(f"the view looks blank (std {std:.1f}, drawn {drawn:.2f}); {out} not saved", file=sys.stderr)
        return False
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(png)
    print(f"wrote {out} at iteration {app.state.iteration}")
    return True


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "screenshot.png")
    ap.add_argument("--inspect-out", type=Path, default=ROOT / "docs" / "inspect.png")
    ap.add_argument("--particles", type=int, default=128)
    ap.add_argument("--iterations", type=int, default=15, help="iterations to run before the pictures")
    ap.add_argument("--rank", type=int, default=5, help="the particle shown before and after physics")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--scene", type=int, default=None)
    ap.add_argument("--frame", type=int, default=None)
    args = ap.parse_args()
    if args.dataset is not None:
        return real_frame(args)

    handle = serve(demo=True, block=False, port=free_port(), workers=args.workers,
                   config=EstimatorConfig(particles=args.particles, iterations=200))
    app = handle.app
    try:
        if not app.wait_for(lambda s: s.view is not None or s.failures, 180) or app.state.view is None:
            print(f"the demo did not load: {app.state.failures}", file=sys.stderr)
            return 1
        with chromium() as browser:
            page = open_workbench(browser, handle.url)
            page.get_by_role("button", name="Run").click()
            app.wait_for(lambda s: s.iteration >= args.iterations, 300)
            app.send(p.Pause())  # hold still for the pictures
            app.wait_for(lambda s: not s.running, 60)
            page.get_by_role("tab", name="Plots").click()
            if not save(page, args.out, app):
                return 1
            page.get_by_role("tab", name="Inspect").click()
            app.panel.scene_mode.value = "before + after"  # shared GUI state: the page follows
            app.display.toggle("particles")  # the chosen particle alone, over the observation
            app.pick(args.rank)
            app.wait_for(lambda s: s.chosen is not None and s.chosen.rank == args.rank, 60)
            if not save(page, args.inspect_out, app):
                return 1
    finally:
        handle.stop()
    return 0


def real_frame(args) -> int:
    """One picture of a dataset's frame mid-run, from the sensor, with its ground truth."""
    from workbench.app.camera import FROM_SENSOR

    handle = serve(args.dataset, args.scene, args.frame, block=False, port=free_port(), workers=args.workers,
                   config=EstimatorConfig(particles=args.particles, iterations=200))
    app = handle.app
    try:
        if not app.wait_for(lambda s: s.view is not None or s.failures, 300) or app.state.view is None:
            print(f"the frame did not load: {app.state.failures}", file=sys.stderr)
            return 1
        with chromium() as browser:
            page = open_workbench(browser, handle.url, viewport={"width": 1600, "height": 1000})
            page.get_by_role("button", name="Run").click()
            app.wait_for(lambda s: s.iteration >= args.iterations or (s.last_state is not None and not s.running
                                                                       and s.iteration >= 0), 900)
            app.send(p.Pause())
            app.wait_for(lambda s: not s.running, 120)
            app.wait_for(lambda s: s.truth is not None and s.truth.iteration == s.iteration, 60)
            app.display.toggle("particles")  # the estimate, the points and the truth, each told apart
            app.cameras.preset(app.state.view, FROM_SENSOR, None)
            if not save(page, args.out, app):
                return 1
    finally:
        handle.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
