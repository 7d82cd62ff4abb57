"""Chromium's CPU use with the workbench open: with the page idle, then during Run.

    .venv/bin/python benchmarks/browser_cpu.py [--seconds 20] [--particles 128] [--root DIR]

Serves the demo (2 evaluation workers), opens it in headless Chromium (software WebGL, as in the tests) at
1280x800, waits until the frame is drawn, then samples the CPU time of every Chromium process for ``--seconds``
with nothing happening, and again while the estimator runs. Printed per Chromium process type (browser, GPU,
renderer, ...) as percent of one core. ``--root`` imports the workbench from another checkout (e.g. an older
commit unpacked with ``git archive``) to compare before and after a change with the same script.
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import time
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def chromium_processes() -> dict[int, str]:
    """pid -> Chromium process type, for the Chromium processes descended from this one."""
    import psutil

    out = {}
    for child in psutil.Process(os.getpid()).children(recursive=True):
        try:
            cmd = child.cmdline()
        except psutil.Error:
            continue
        if not cmd or "chrom" not in os.path.basename(cmd[0]):
            continue
        kind = next((a.split("=", 1)[1] for a in cmd if a.startswith("--type=")), "browser")
        out[child.pid] = kind
    return out


def cpu_seconds(pids: dict[int, str]) -> dict[str, float]:
    """Process type -> user + system CPU seconds so far, summed over the processes of that type."""
    import psutil

    total: dict[str, float] = {}
    for pid, kind in pids.items():
        try:
            t = psutil.Process(pid).cpu_times()
        except psutil.Error:
            continue
        total[kind] = total.get(kind, 0.0) + t.user + t.system
    return total


def sample(seconds: float) -> dict[str, float]:
    """Percent of one core per Chromium process type over the next ``seconds``."""
    pids = chromium_processes()
    a, t0 = cpu_seconds(pids), time.monotonic()
    time.sleep(seconds)
    b, t1 = cpu_seconds(pids), time.monotonic()
    return {k: 100.0 * (b.get(k, 0.0) - a.get(k, 0.0)) / (t1 - t0) for k in sorted(set(a) | set(b))}


def show(label: str, use: dict[str, float]) -> None:
    parts = " · ".join(f"{k} {v:.0f} %" for k, v in use.items())
    print(f"{label:<8} total {sum(use.values()):.0f} % of a core ({parts})", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--particles", type=int, default=128)
    ap.add_argument("--root", type=Path, default=Path(__file__).resolve().parent.parent)
    args = ap.parse_args()
    sys.path.insert(0, str(args.root.resolve()))

    from workbench.app import protocol as p
    from workbench.app.headless import chromium, dismiss_notifications, open_workbench
    from workbench.app.server import serve
    from workbench.estimators import EstimatorConfig

    import workbench

    print(f"workbench from {Path(workbench.__file__).parent}", flush=True)
    handle = serve(demo=True, block=False, port=free_port(), workers=2,
                   config=EstimatorConfig(particles=args.particles, iterations=100_000))
    app = handle.app
    try:
        if not app.wait_for(lambda s: s.view is not None or s.failures, 180) or app.state.view is None:
            print(f"the demo did not load: {app.state.failures}", file=sys.stderr)
            return 1
        with chromium() as browser:
            page = open_workbench(browser, handle.url)
            dismiss_notifications(page, wait_ms=10_000)
            time.sleep(5.0)  # the first frames, fonts, layout
            show("idle", sample(args.seconds))
            start = app.state.iteration
            app.send(p.Run(False))
            app.wait_for(lambda s: s.iteration >= start + 2, 120)
            use = sample(args.seconds)
            done = app.state.iteration - start
            app.send(p.Pause())
            show("running", use)
            print(f"         ({done} iterations meanwhile, {args.particles} particles)")
            app.wait_for(lambda s: not s.running, 60)
            time.sleep(3.0)
            show("idle", sample(args.seconds))
    finally:
        handle.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
