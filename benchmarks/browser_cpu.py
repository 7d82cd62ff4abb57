"""Chromium's CPU use with the workbench open: with the page idle, then during Run.

    .venv/bin/python benchmarks/browser_cpu.py [--seconds 20] [--particles 128] [--root DIR]
                                               [--dataset DIR --scene ID --frame ID]

``--dataset``: a BOP frame instead of the demo (e.g. ../shared/datasets/ycbv-real-dev --scene 1 --frame 1); the
ground truth is shown (where an older checkout hides it by default, it is switched on), with the particles.

Serves the demo (2 evaluation workers), opens it in headless Chromium (software WebGL, as in the tests) at
1280x800, waits until the frame is drawn, then samples for ``--seconds`` each: with nothing happening, while the
estimator runs, and after it was paused. Printed per phase:

- the CPU time of every Chromium process, per process type (browser, GPU, renderer, ...), as percent of one core;
- measures that do not depend on the machine's load: frames the page drew with WebGL per second, WebGL calls per
  frame, requestAnimationFrame callbacks per second, running CSS animations, and the server's messages that make
  the 3D view draw ("scene messages", most frequent types named) per second and the bursts they came in (each
  burst makes viser's client draw frames for 250 ms); and CPU milliseconds per drawn frame.

``--layers`` then samples the paused page again with each layer of the visibility bar hidden in turn (points,
particles, estimate, modes, truth): what each layer's drawing costs is the paused cost less that sample's.

``--root`` imports the served workbench from another checkout (e.g. an older commit unpacked with ``git archive``)
to compare before and after a change with the same script; the browser and the probes always come from this
checkout's ``tests/headless.py``, loaded by path, so both runs are measured alike.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from collections import Counter
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent
LAYERS = ("points", "particles", "estimate", "modes", "truth")  # --layers: each hidden in turn, the others shown


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


def load_probes():
    """This checkout's ``tests/headless.py`` as a module of its own (not ``--root``'s)."""
    spec = importlib.util.spec_from_file_location("_probes", HERE / "tests" / "headless.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def sample(seconds: float, page, sent, probes) -> dict:
    """Over the next ``seconds``: percent of one core per Chromium process type (``cpu``), the page's frame counts'
    increase (``frames``, ``draws``, ``callbacks``; ``animations`` running at the end), the scene messages sent
    (``scene``: type name -> count), the bursts they came in (``redraws``) and the wall time (``seconds``)."""
    pids = chromium_processes()
    f0 = probes.frame_counts(page)
    a, t0 = cpu_seconds(pids), time.monotonic()
    time.sleep(seconds)
    b, t1 = cpu_seconds(pids), time.monotonic()
    f1 = probes.frame_counts(page)
    return {
        "cpu": {k: 100.0 * (b.get(k, 0.0) - a.get(k, 0.0)) / (t1 - t0) for k in sorted(set(a) | set(b))},
        **{k: f1[k] - f0[k] for k in ("frames", "draws", "callbacks")},
        "animations": f1["animations"],
        "scene": Counter(sent.scene_since(t0, t1)),
        "redraws": len(sent.redraws(t0, t1)),
        "seconds": t1 - t0,
    }


def show(label: str, m: dict) -> None:
    """Print one phase's measures (``m`` from ``sample``)."""
    use, dt = m["cpu"], m["seconds"]
    parts = " · ".join(f"{k} {v:.0f} %" for k, v in use.items())
    print(f"{label:<8} total {sum(use.values()):.0f} % of a core ({parts})", flush=True)
    frames = m["frames"]
    per_frame = f"{10.0 * sum(use.values()) * dt / frames:.0f} ms CPU" if frames else "no frames"
    top = ", ".join(f"{name} {n / dt:.1f}" for name, n in m["scene"].most_common(4))
    print(f"         {frames / dt:.1f} frames/s ({m['draws'] / max(frames, 1):.0f} WebGL calls each, {per_frame} "
          f"each) · {m['callbacks'] / dt:.1f} animation callbacks/s · {m['animations']} CSS animations running",
          flush=True)
    print(f"         {sum(m['scene'].values()) / dt:.1f} scene messages/s in {m['redraws'] / dt:.1f} bursts/s"
          f"{' (' + top + ')' if top else ''}", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--particles", type=int, default=128)
    ap.add_argument("--root", type=Path, default=HERE)
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--scene", type=int, default=None)
    ap.add_argument("--frame", type=int, default=None)
    ap.add_argument("--layers", action="store_true",
                    help="after the paused phase, sample again with each layer of the visibility bar hidden in turn")
    args = ap.parse_args()
    probes = load_probes()
    sys.path.insert(0, str(args.root.resolve()))

    free_port = probes.free_port
    import workbench
    from workbench.app import protocol as p
    from workbench.app.ui.server import serve
    from workbench.inference.config import EstimatorConfig

    print(f"workbench from {Path(workbench.__file__).parent}", flush=True)
    where = {"demo": True} if args.dataset is None else {"dataset": args.dataset, "scene_id": args.scene,
                                                          "im_id": args.frame}
    handle = serve(block=False, port=free_port(), workers=2,
                   config=EstimatorConfig(particles=args.particles, iterations=100_000), **where)
    app = handle.app
    try:
        if not app.wait_for(lambda s: s.view is not None or s.failures, 180) or app.state.view is None:
            print(f"the frame did not load: {app.state.failures}", file=sys.stderr)
            return 1
        panel = getattr(app, "panel", None)  # an older checkout's: its ground truth was hidden by default
        if panel is not None and hasattr(panel, "show_gt"):
            panel.show_gt.value = True
        print(f"{app.state.view.title}: ground truth "
              f"{'shown' if app.state.view.gt_T_world_obj is not None else 'absent'}, particles shown", flush=True)
        with probes.chromium() as browser, probes.SentMessages().record() as sent:
            page = probes.open_workbench(browser, handle.url, init_script=probes.FRAME_PROBE_JS)
            probes.dismiss_notifications(page, wait_ms=10_000)
            time.sleep(5.0)  # the first frames, fonts, layout
            show("idle", sample(args.seconds, page, sent, probes))
            start = app.state.iteration
            app.send(p.Run(False))
            app.wait_for(lambda s: s.iteration >= start + 2, 120)
            running = sample(args.seconds, page, sent, probes)
            done = app.state.iteration - start
            app.send(p.Pause())
            show("running", running)
            print(f"         ({done} iterations meanwhile, {args.particles} particles)")
            app.wait_for(lambda s: not s.running, 60)
            time.sleep(3.0)
            show("paused", sample(args.seconds, page, sent, probes))
            for layer in LAYERS if args.layers else ():
                page.get_by_role("button", name=f"● {layer}").click()
                time.sleep(2.0)
                show(f"-{layer}", sample(args.seconds, page, sent, probes))
                page.get_by_role("button", name=f"○ {layer}").click()
                time.sleep(2.0)
    finally:
        handle.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
