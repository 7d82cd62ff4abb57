"""Save the README screenshots, in headless Chromium on the demo frame, each once the run finished (``--iterations``,
its budget) and so has its posterior:

- docs/screenshot.png: the Plots tab beside the 3D view, with the legend unfolded (each object's confidence) and
  the estimate's other modes drawn as ghosts where it has any;
- docs/inspect.png: the Inspect tab, the posterior's table, one particle before (outline) and after physics, and
  how physics moved it.

    python scripts/screenshot.py [--out docs/screenshot.png] [--inspect-out docs/inspect.png] [--particles 128]
                                 [--iterations 15] [--rank 5]

With ``--dataset DIR [--scene ID --frame ID]`` (e.g. ../shared/datasets/ycbv-real-seq --scene 1 --frame 1), one
picture of that frame once its run finished, its objects framed, at 1600x1000: the estimate (solid), the observed
points (grey), the ground truth (black outlines), the table of errors against it with each object's confidence, and
the Data tab with the frame's colour image where the dataset has ``rgb/``, into ``--out`` (docs/ycbv.png in the
README).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # the browser test tooling

from headless import chromium, dismiss_notifications, free_port, image_stats, open_workbench  # noqa: E402

from workbench.app.ui.server import serve  # noqa: E402
from workbench.inference.config import EstimatorConfig  # noqa: E402

MAX_BYTES = 400_000  # a README picture larger than this is stored with a palette of 256 colours


def fewer_colours(png: bytes) -> bytes:
    """``png`` again with an adaptive palette of 256 colours: the grey points' noise makes a full-colour page
    several hundred kB."""
    import io

    from PIL import Image

    out = io.BytesIO()
    Image.open(io.BytesIO(png)).convert("RGB").quantize(256, dither=Image.Dither.NONE).save(out, "PNG", optimize=True)
    return out.getvalue()


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
    out.write_bytes(png if len(png) <= MAX_BYTES else fewer_colours(png))
    print(f"wrote {out} at iteration {app.state.iteration}")
    return True


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "screenshot.png")
    ap.add_argument("--inspect-out", type=Path, default=ROOT / "docs" / "inspect.png")
    ap.add_argument("--particles", type=int, default=128)
    ap.add_argument("--iterations", type=int, default=15, help="the run's budget: the pictures show its end")
    ap.add_argument("--rank", type=int, default=5, help="the particle shown before and after physics")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--scene", type=int, default=None)
    ap.add_argument("--frame", type=int, default=None)
    args = ap.parse_args()
    if args.dataset is not None:
        return real_frame(args)

    handle = serve(demo=True, block=False, port=free_port(), workers=args.workers,
                   config=EstimatorConfig(particles=args.particles, iterations=args.iterations))
    app = handle.app
    try:
        if not app.wait_for(lambda s: s.view is not None or s.failures, 180) or app.state.view is None:
            print(f"the demo did not load: {app.state.failures}", file=sys.stderr)
            return 1
        with chromium() as browser:
            page = open_workbench(browser, handle.url)
            if not run_to_the_end(page, app, 600):
                return 1
            page.get_by_text("Legend", exact=True).click()  # folded by default: the confidences are in it
            page.get_by_role("button", name="Step").scroll_into_view_if_needed()  # the panel's top in the picture
            page.get_by_role("tab", name="Plots").click()
            if not save(page, args.out, app):
                return 1
            page.get_by_role("tab", name="Inspect").click()
            page.get_by_text("Legend", exact=True).click()  # folded again: the posterior's table in the picture
            page.get_by_text("of the settled estimate").scroll_into_view_if_needed()
            app.display.inspect.scene_mode.value = "before + after"  # shared GUI state: the page follows
            app.toggle("particles")  # the chosen particle alone, over the observation
            app.pick(args.rank)
            app.wait_for(lambda s: s.chosen is not None and s.chosen.rank == args.rank, 60)
            if not save(page, args.inspect_out, app):
                return 1
    finally:
        handle.stop()
    return 0


def run_to_the_end(page, app, timeout_s: float) -> bool:
    """Run until the budget or convergence, and wait until the posterior and the truth table of the last iteration
    are shown -> whether they are."""
    page.get_by_role("button", name="Run").click()
    done = app.wait_for(lambda s: s.iteration >= 0 and not s.running and s.last_state is not None
                        and s.last_state.reason in ("converged", "done"), timeout_s)
    if not done or not app.wait_for(lambda s: s.truth is None or s.truth.iteration == s.iteration, 60):
        print(f"the run did not finish in {timeout_s:.0f} s (iteration {app.state.iteration})", file=sys.stderr)
        return False
    return True


def real_frame(args) -> int:
    """One picture of a dataset's frame once its run finished, its objects framed, with its ground truth and (where
    the dataset has one) its colour image."""
    from workbench.app.ui.run.camera import FRAME_OBJECTS

    handle = serve(args.dataset, args.scene, args.frame, block=False, port=free_port(), workers=args.workers,
                   config=EstimatorConfig(particles=args.particles, iterations=args.iterations))
    app = handle.app
    try:
        if not app.wait_for(lambda s: s.view is not None or s.failures, 300) or app.state.view is None:
            print(f"the frame did not load: {app.state.failures}", file=sys.stderr)
            return 1
        with chromium() as browser:
            page = open_workbench(browser, handle.url, viewport={"width": 1600, "height": 1000})
            if not run_to_the_end(page, app, 1200):
                return 1
            app.toggle("particles")  # the estimate, the points and the truth, each told apart
            app.cameras.preset(app.state.view, FRAME_OBJECTS, None)
            if app.state.view.rgb_image is not None:
                page.get_by_role("tab", name="Data").click()  # the colour image beside the 3D view
            if not save(page, args.out, app):
                return 1
    finally:
        handle.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
