"""A soak of ``workbench track``: a generated sequence tracked once undisturbed, and once with an evaluation worker
killed every ``--kill-every`` seconds and the run itself killed (SIGKILL) twice and resumed with ``--resume``. It
reports whether every frame is there once, whether the rows equal the undisturbed run's (all columns but the time),
the longest silence on stderr within each run, and what was killed.

    PYTHONPATH=. .venv/bin/python benchmarks/track_soak.py --frames 200 --out bench-out/soak

The sequence: ``make-scenes --categories touching --sequence FRAMES`` (two boxes), at ``--width`` x ``--height``.
"""

from __future__ import annotations

import argparse
import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FIRST = ["--particles", "100", "--iterations", "8"]  # the first frame's budget: two generated boxes


def workers_of(pid: int) -> list[int]:
    """The evaluation workers of process ``pid``: its children started by multiprocessing (Linux /proc), not its
    resource tracker."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            if parent == pid and "spawn_main" in command:
                out.append(int(entry.name))
    return out


class Run:
    """One ``workbench track`` process; its stderr lines are timed as they come (``silence``)."""

    def __init__(self, args: list[str]):
        self.proc = subprocess.Popen([sys.executable, "-m", "workbench.cli", "track", *args], cwd=ROOT,
                                     stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
        self.lines: list[tuple[float, str]] = []
        self.started = time.monotonic()
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append((time.monotonic(), line.rstrip()))

    def silence(self) -> tuple[float, str]:
        """The longest gap between stderr lines (s) and the line it followed ("(start)" for the first)."""
        marks = [(self.started, "(start)")] + self.lines
        if len(marks) == 1:
            return time.monotonic() - self.started, "(start)"
        return max((b[0] - a[0], a[1]) for a, b in zip(marks, marks[1:]))

    def wait(self) -> int:
        code = self.proc.wait()
        self.reader.join(5)
        return code


def frames_written(csv: Path) -> int:
    if not csv.exists():
        return 0
    return len({line.split(",")[1] for line in csv.read_text().splitlines()[1:] if line})


def untimed(csv: Path) -> list[str]:
    return [line.rsplit(",", 1)[0] for line in csv.read_text().splitlines()]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--kill-every", type=float, default=30.0, help="seconds between killed workers")
    ap.add_argument("--out", type=Path, default=ROOT / "bench-out" / "soak")
    args = ap.parse_args()
    from workbench.synth.sequence import make_sequences

    args.out.mkdir(parents=True, exist_ok=True)
    data = args.out / "seq"
    if not (data / "test" / "000000" / "scene_camera.json").exists():
        make_sequences(data, ["touching"], 1, args.frames, seed=0, width=args.width, height=args.height, force=True)
    common = [str(data), "--scene", "0", "--workers", "2", *FIRST]

    calm_csv, soak_csv = args.out / "undisturbed.csv", args.out / "soaked.csv"
    t0 = time.monotonic()
    calm = Run([*common, "--out", str(calm_csv), "--force"])
    if calm.wait() != 0:
        print("the undisturbed run failed:\n" + "\n".join(line for _, line in calm.lines[-20:]), file=sys.stderr)
        return 1
    calm_s = time.monotonic() - t0
    gap, after = calm.silence()
    print(f"undisturbed: {frames_written(calm_csv)} frames in {calm_s:.0f} s, longest silence {gap:.1f} s after "
          f"{after!r}", flush=True)

    # Disturbed: the run killed once a third and two thirds of the frames are written, resumed each time; a worker
    # killed every --kill-every seconds throughout.
    soak_csv.unlink(missing_ok=True)
    runs, workers_killed, stops = [], 0, [args.frames // 3, 2 * args.frames // 3]
    t0 = time.monotonic()
    while True:
        run = Run([*common, "--out", str(soak_csv), "--resume" if runs else "--force"])
        runs.append(run)
        last_kill = time.monotonic()
        while run.proc.poll() is None:
            time.sleep(0.5)
            if time.monotonic() - last_kill >= args.kill_every:
                workers = workers_of(run.proc.pid)
                if workers:
                    os.kill(workers[0], signal.SIGKILL)
                    workers_killed += 1
                last_kill = time.monotonic()
            if stops and frames_written(soak_csv) >= stops[0]:
                stops.pop(0)
                run.proc.kill()
                break
        code = run.wait()
        if code == 0:
            break
        if code != -signal.SIGKILL:
            print(f"a disturbed run failed with exit code {code}:\n" + "\n".join(line for _, line in run.lines[-20:]),
                  file=sys.stderr)
            return 1
    soak_s = time.monotonic() - t0
    calm_rows, soak_rows = untimed(calm_csv), untimed(soak_csv)
    blocks = [im for im, _ in itertools.groupby(line.split(",")[1] for line in soak_rows[1:])]
    each_once = len(blocks) == len(set(blocks)) == args.frames  # each frame's rows once, together
    same = soak_rows == calm_rows
    silence, after = max(r.silence() for r in runs)
    print(f"disturbed: {len(runs)} runs (killed {len(runs) - 1} times, resumed with --resume), {workers_killed} "
          f"workers killed, {soak_s:.0f} s; every frame once: {each_once}; rows equal the undisturbed run's "
          f"(all but the time): {same}; longest silence {silence:.1f} s after {after!r}")
    return 0 if each_once and same and silence <= 10.0 else 1


if __name__ == "__main__":
    sys.exit(main())
