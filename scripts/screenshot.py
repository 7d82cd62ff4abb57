"""Save the README screenshot (docs/screenshot.png): the workbench on the demo frame, mid-run, in headless Chromium.

    python scripts/screenshot.py [--out docs/screenshot.png] [--particles 128] [--iterations 6]
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
from workbench.estimators import EstimatorConfig  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "screenshot.png")
    ap.add_argument("--particles", type=int, default=128)
    ap.add_argument("--iterations", type=int, default=6, help="iterations to run before the picture")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()

    handle = serve(demo=True, block=False, port=free_port(), workers=args.workers,
                   config=EstimatorConfig(particles=args.particles, iterations=200))
    app = handle.app
    try:
        if not app.wait_for(lambda s: s.view is not None or s.failures, 180) or app.state.view is None:
            print(f"the demo did not load: {app.state.failures}", file=sys.stderr)
            return 1
        with chromium() as browser:
            page = open_workbench(browser, handle.url)
            page.get_by_role("tab", name="Inspect").click()
            app.point_cameras(app.state.view, zoom=1.8)
            app.panel.heatmap_mode.value = "log-likelihood"  # shared GUI state: the page follows
            page.get_by_role("button", name="Run").click()
            app.wait_for(lambda s: s.iteration >= args.iterations, 300)
            app.send(p.Pause())  # hold still for the picture; the panel still shows the last running state
            app.wait_for(lambda s: not s.running, 60)
            time.sleep(2.0)  # let SwiftShader catch up with the last updates
            dismiss_notifications(page, wait_ms=10_000)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            png = page.screenshot()
            std, drawn = image_stats(png)
            if drawn < 0.05:
                print(f"the view looks blank (std {std:.1f}, drawn {drawn:.2f}); not saved", file=sys.stderr)
                return 1
            args.out.write_bytes(png)
            print(f"wrote {args.out} at iteration {app.state.iteration}")
    finally:
        handle.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
