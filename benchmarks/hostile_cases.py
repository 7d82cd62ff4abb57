"""Hostile cases, tried as a new user would: the command line run as a subprocess on a fresh copy of the demo
dataset (assets/demo) per case, with damaged inputs, outputs that must not be written, concurrent runs, damaged
caches, a killed worker, bad parameters. Prints one line per case and "N of M handled".

A case is *handled* when the command ends as expected, with no traceback on stderr:
- ``error``: exit code 2 and ``workbench: error: FILE: problem``, naming what the case names;
- ``ok`` / ``warn``: exit code 0 (``warn``: with a WARNING naming what the case names);
and, whatever the outcome, every file the user had (the dataset copy, their notes, their results) is left as it
was, except the output the case allows to be written.

    .venv/bin/python benchmarks/hostile_cases.py [--quick] [--only WORD]

``--quick`` skips the cases that run a real estimate (caches, a killed worker, SIGTERM, a session, a 1.3M-face
model; a few minutes in all), ``--slow-only`` runs only those. The render-mesh cache is not among them: the demo's
meshes are too small to be decimated (tests/test_outputs_and_workers.py damages one directly). Extends the
ideas of tests/test_bad_input_fuzzed.py (which mutates every JSON field and the depth image in-process) with the
cases of issue 34. Needs no ../shared.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parent.parent
DEMO = ROOT / "assets" / "demo"
WORKBENCH = [sys.executable, "-m", "workbench.cli"]
TINY = ["--particles", "16", "--iterations", "1", "--no-settle"]
ROW = "0,0,5,1,1 0 0 0 1 0 0 0 1,0 0 500,1.0"
HEADER = "scene_id,im_id,obj_id,score,R,t,time"


@dataclass
class Case:
    name: str
    setup: Callable[[Path], list[str]]  # workspace -> argv after `workbench`
    expect: str = "error"  # error | ok | warn
    words: tuple[str, ...] = ()
    writes: tuple[str, ...] = ()  # workspace-relative files the command may write
    slow: bool = False
    during: Callable[[subprocess.Popen, Path], None] | None = None  # runs beside the command
    env: dict = field(default_factory=dict)
    max_silence_s: float | None = None  # the longest stderr may go without a line (from the start to the exit)


# ----------------------------------------------------------------------------------------------------------------
# Helpers for the set-ups

def ds(ws: Path) -> Path:
    return ws / "demo"


def scene(ws: Path) -> Path:
    return ds(ws) / "test" / "000000"


def edit_json(path: Path, change: Callable[[dict], object]) -> None:
    doc = json.loads(path.read_text())
    out = change(doc)
    path.write_text(json.dumps(doc if out is None else out))


def cam(change):
    return lambda ws: (edit_json(scene(ws) / "scene_camera.json", change), estimate(ws))[1]


def gt(change):
    return lambda ws: (edit_json(scene(ws) / "scene_gt.json", change), estimate(ws))[1]


def info(change):
    return lambda ws: (edit_json(ds(ws) / "models" / "models_info.json", change), estimate(ws))[1]


def estimate(ws: Path, *extra: str, out: str = "r.csv") -> list[str]:
    return ["estimate", str(ds(ws)), *TINY, "--out", str(ws / out), *extra]


def write(rel: str, data: bytes | str):
    def setup(ws: Path) -> list[str]:
        p = ws / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data.encode() if isinstance(data, str) else data)
        return estimate(ws)
    return setup


def remove(rel: str):
    def setup(ws: Path) -> list[str]:
        p = ws / rel
        shutil.rmtree(p) if p.is_dir() else p.unlink()
        return estimate(ws)
    return setup


def png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def results(ws: Path, *rows: str, name: str = "r.csv", prefix: bytes = b"") -> Path:
    p = ws / name
    p.write_bytes(prefix + (HEADER + "\n" + "".join(r + "\n" for r in rows)).encode())
    return p


def notes(ws: Path) -> Path:
    p = ws / "notes.txt"
    p.write_text("my notes\n")
    return p


def depth_png(ws: Path) -> Path:
    return scene(ws) / "depth" / "000000.png"


def scale_mesh(factor: float):
    def setup(ws: Path) -> list[str]:
        import trimesh

        ply = ds(ws) / "models" / "obj_000005.ply"
        mesh = trimesh.load(ply)
        mesh.apply_scale(factor)
        mesh.export(ply)
        return estimate(ws)
    return setup


def heavy_model(ws: Path) -> list[str]:
    """obj_000006 replaced by a 1.3M-face sphere (icosphere(8), 5 cm radius, in mm as BOP's models), its
    models_info.json entry to match (no symmetries listed), estimated with the render and collision caches cold for
    it."""
    import trimesh

    sphere = trimesh.creation.icosphere(8, radius=50.0)
    (ds(ws) / "models" / "obj_000006.ply").write_bytes(sphere.export(file_type="ply"))
    lo, size = sphere.bounds[0], sphere.extents
    entry = {"diameter": 100.0, **{f"min_{a}": float(lo[i]) for i, a in enumerate("xyz")},
             **{f"size_{a}": float(size[i]) for i, a in enumerate("xyz")}}
    edit_json(ds(ws) / "models" / "models_info.json", lambda doc: {**doc, "6": entry})
    return estimate(ws)


def upsampled(ws: Path) -> list[str]:
    image = Image.open(depth_png(ws))
    image.resize((image.width * 2, image.height * 2), Image.NEAREST).save(depth_png(ws))
    (ds(ws) / "camera.json").unlink()
    return estimate(ws)


def locked(ws: Path) -> list[str]:
    results(ws, ROW)
    return estimate(ws, "--resume")


def hold_lock(proc_unused, ws: Path):  # set up before the command: see run_case
    pass


SAVE_SESSION = """
import sys
from pathlib import Path
from workbench.inference.estimator import Estimator
from workbench.evaluation import LocalEvaluator
from workbench.inference.config import EstimatorConfig
from workbench.problem.build import load_bop_problem
from workbench.sessions import store as sessions
demo, folder = Path(sys.argv[1]), Path(sys.argv[2])
frame, problem = load_bop_problem(demo, 0, 0)
ev = LocalEvaluator(problem)
est = Estimator(problem, EstimatorConfig(particles=6, iterations=10, seed=1), ev)
est.step()
state = sessions.session_state_from(est, sessions.frame_ref_for(demo, frame, problem), [None, None])
sessions.save_session(folder, "run", state)
ev.close()
"""


def session_of_deleted_dataset(ws: Path) -> list[str]:
    """A real saved session (one step on a copy of the demo) whose dataset folder is then deleted."""
    other = ws / "other"
    shutil.copytree(DEMO, other)
    subprocess.run([sys.executable, "-c", SAVE_SESSION, str(other), str(ws / "sessions")], env=env_for(ws),
                   capture_output=True, check=True)
    shutil.rmtree(other)
    return ["serve", "--session", str(ws / "sessions" / "run.json"), "--port", "18391"]


# ----------------------------------------------------------------------------------------------------------------
# The cases

def cases() -> list[Case]:
    c: list[Case] = []
    E = "error"
    # -- the dataset's camera file
    c += [
        Case("scene_camera.json missing", remove("demo/test/000000/scene_camera.json"), E, ("scene_camera.json",)),
        Case("scene_camera.json empty", write("demo/test/000000/scene_camera.json", ""), E, ("scene_camera.json",)),
        Case("scene_camera.json cut short", write("demo/test/000000/scene_camera.json", '{"0": {"cam_K": [1'), E,
             ("scene_camera.json",)),
        Case("scene_camera.json a list", write("demo/test/000000/scene_camera.json", "[1, 2]"), E,
             ("scene_camera.json",)),
        Case("scene_camera.json with a BOM", lambda ws: (
            (scene(ws) / "scene_camera.json").write_bytes(b"\xef\xbb\xbf" + (scene(ws) / "scene_camera.json")
                                                          .read_bytes()), estimate(ws))[1], E, ("BOM",)),
        Case("cam_K a string", cam(lambda d: d["0"].__setitem__("cam_K", "abc")), E, ("cam_K",)),
        Case("cam_K of 8 numbers", cam(lambda d: d["0"].__setitem__("cam_K", d["0"]["cam_K"][:8])), E, ("cam_K",)),
        Case("cam_K with NaN", cam(lambda d: d["0"]["cam_K"].__setitem__(0, float("nan"))), E, ("cam_K",)),
        Case("depth_scale 0", cam(lambda d: d["0"].__setitem__("depth_scale", 0)), E, ("depth_scale",)),
        Case("depth_scale negative", cam(lambda d: d["0"].__setitem__("depth_scale", -1)), E, ("depth_scale",)),
        Case("depth_scale a string", cam(lambda d: d["0"].__setitem__("depth_scale", "1")), E, ("depth_scale",)),
        Case("depth_scale: table 100 m away", cam(lambda d: d["0"].__setitem__("depth_scale", 1000.0)), E,
             ("depth_scale",)),
        Case("cam_t_w2c in metres", cam(lambda d: d["0"].__setitem__("cam_t_w2c", [1e6, 0, 0])), E,
             ("cam_t_w2c",)),
        Case("cam_R_w2c a reflection", cam(lambda d: d["0"].__setitem__("cam_R_w2c", [-1, 0, 0, 0, 1, 0, 0, 0, 1])),
             E, ("cam_R_w2c",)),
        Case("depth image of another resolution than cam_K", upsampled, E, ("another resolution",)),
    ]
    # -- ground truth and models
    c += [
        Case("scene_gt.json not JSON", write("demo/test/000000/scene_gt.json", "{not json"), E, ("scene_gt.json",)),
        Case("scene_gt obj_id a string", gt(lambda d: d["0"][0].__setitem__("obj_id", "five")), E, ("obj_id",)),
        Case("scene_gt cam_t_m2c NaN", gt(lambda d: d["0"][0].__setitem__("cam_t_m2c", [float("nan"), 0, 0])), E,
             ("scene_gt.json",)),
        Case("scene_gt rotation not a rotation", gt(lambda d: d["0"][0].__setitem__("cam_R_m2c", [1] * 9)), E,
             ("scene_gt.json",)),
        Case("models_info.json missing", remove("demo/models/models_info.json"), E, ("models_info.json",)),
        Case("models_info keys not ids", info(lambda d: {"five": v for v in d.values()}), E, ("models_info.json",)),
        Case("models_info a list", info(lambda d: [1]), E, ("models_info.json",)),
        Case("model file missing", remove("demo/models/obj_000005.ply"), E, ("obj_000005.ply",)),
        Case("model file empty", write("demo/models/obj_000005.ply", ""), E, ("obj_000005.ply",)),
        Case("model file garbage", write("demo/models/obj_000005.ply", "ply\ngarbage\n"), E, ("obj_000005.ply",)),
        Case("model 1000x too small (metres)", scale_mesh(1e-3), E, ("metres",)),
        Case("model 1000x too large", scale_mesh(1e3), E, ("micrometres",)),
        Case("depth image missing", remove("demo/test/000000/depth/000000.png"), E, ("000000.png",)),
        Case("depth image empty", write("demo/test/000000/depth/000000.png", b""), E, ("000000.png",)),
        Case("depth image cut short", lambda ws: (depth_png(ws).write_bytes(depth_png(ws).read_bytes()[:500]),
                                                  estimate(ws))[1], E, ("000000.png",)),
        Case("depth image 8-bit colour", write("demo/test/000000/depth/000000.png",
                                               png(np.zeros((480, 640, 3), np.uint8))), E, ("000000.png",)),
        Case("depth image all zeros", write("demo/test/000000/depth/000000.png",
                                            png(np.zeros((480, 640), np.uint16))), E, ("000000.png",)),
    ]
    # -- where results go
    c += [
        Case("--out a folder", lambda ws: estimate(ws, out="."), E, ("is a folder",)),
        Case("--out below a file", lambda ws: (notes(ws), estimate(ws, out="notes.txt/r.csv"))[1], E, ("is a file",)),
        Case("--out a scene's scene_gt.json", lambda ws: estimate(ws, out="demo/test/000000/scene_gt.json"), E,
             ("dataset folder",)),
        Case("--out a scene's scene_gt.json --force", lambda ws: estimate(ws, "--force",
                                                                          out="demo/test/000000/scene_gt.json"), E,
             ("dataset folder",)),
        Case("--out the dataset's camera.json --force", lambda ws: estimate(ws, "--force", out="demo/camera.json"),
             E, ("never replaced",)),
        Case("--out a user's notes", lambda ws: (notes(ws), estimate(ws, out="notes.txt"))[1], E, ("--force",)),
        Case("--out /dev/full", lambda ws: ["estimate", str(ds(ws)), "--out", "/dev/full"], E, ("regular file",)),
        *([] if os.geteuid() == 0 else [  # root writes anywhere: the case means nothing there
            Case("--out in a read-only folder", lambda ws: ((ws / "ro").mkdir(), (ws / "ro").chmod(0o555),
                                                            estimate(ws, out="ro/r.csv"))[2], E, ("permission",))]),
        Case("--resume on a user's file", lambda ws: (notes(ws), estimate(ws, "--resume", out="notes.txt"))[1], E,
             ("nothing to resume",)),
        Case("--resume on another dataset's results", lambda ws: (results(ws, "7,3,5,1,1 0 0 0 1 0 0 0 1,0 0 5,1"),
                                                                  estimate(ws, "--resume"))[1], E,
             ("another dataset",)),
        Case("--resume on a cut last line", lambda ws: (results(ws, ROW, "0,1,5,1,1 0"), estimate(ws, "--resume"))[1],
             E, ("line 3",)),
        Case("--resume on a CSV with a BOM", lambda ws: (results(ws, ROW, prefix=b"\xef\xbb\xbf"),
                                                         estimate(ws, "--resume"))[1], E, ("byte order mark",)),
        Case("--resume with --force", lambda ws: (results(ws, ROW), estimate(ws, "--resume", "--force"))[1], E,
             ("--resume",)),
        Case("a second run on the same --out", locked, E, ("another run", "pid")),
        Case("--split models", lambda ws: estimate(ws, "--split", "models"), E, ("demo",)),
        Case("--scene 99", lambda ws: estimate(ws, "--scene", "99"), E, ("--scene 99",)),
    ]
    # -- score --json, bench --out, sessions
    def score(ws, target, *extra):
        results(ws, ROW)
        return ["score", str(ds(ws)), str(ws / "r.csv"), "--json", str(target), *extra]
    c += [
        Case("score --json the results CSV", lambda ws: score(ws, ws / "r.csv"), E, ("being scored",)),
        Case("score --json a user's notes", lambda ws: (notes(ws), score(ws, ws / "notes.txt"))[1], E, ("--force",)),
        Case("score --json scene_gt.json", lambda ws: score(ws, scene(ws) / "scene_gt.json", "--force"), E,
             ("dataset folder",)),
        Case("score --json camera.json --force", lambda ws: score(ws, ds(ws) / "camera.json", "--force"), E,
             ("never replaced",)),
        Case("score --json a folder", lambda ws: score(ws, ws), E, ("is a folder",)),
        Case("score --json /dev/full", lambda ws: score(ws, "/dev/full"), E, ("regular file",)),
        Case("score --json a new file", lambda ws: score(ws, ws / "s.json"), "ok", writes=("s.json",)),
        Case("score without scene_gt.json",
             lambda ws: ((scene(ws) / "scene_gt.json").unlink(), score(ws, ws / "s.json"))[1],
             E, ("no scene_gt.json",)),
        Case("score a results file that is not one", lambda ws: (notes(ws), ["score", str(ds(ws)),
                                                                           str(ws / "notes.txt")])[1], E,
             ("notes.txt",)),
        Case("bench --out a file", lambda ws: (notes(ws), ["bench", str(ds(ws)), "--out", str(ws / "notes.txt")])[1],
             E, ("is a file",)),
        Case("bench --out in the dataset", lambda ws: ["bench", str(ds(ws)), "--out", str(scene(ws) / "b")], E,
             ("dataset folder",)),
        Case("bench --out holding a user's report.md", lambda ws: ((ws / "b").mkdir(), (ws / "b" / "report.md")
                                                                   .write_text("mine"),
                                                                   ["bench", str(ds(ws)), "--out", str(ws / "b")])[2],
             E, ("report.md",)),
        Case("serve --session missing", lambda ws: ["serve", "--session", str(ws / "none.json")], E, ("none.json",)),
        Case("serve --session garbage", lambda ws: ((ws / "s.json").write_text("{{"),
                                                    ["serve", "--session", str(ws / "s.json")])[1], E, ("s.json",)),
        Case("serve --session of a deleted dataset", session_of_deleted_dataset, E,
             ("run.json", "dataset folder not found"), slow=True),
        Case("serve --sessions-dir a file", lambda ws: (notes(ws), ["serve", "--demo", "--sessions-dir",
                                                                    str(ws / "notes.txt")])[1], E, ("is a file",)),
        Case("serve --port 70000", lambda ws: ["serve", "--demo", "--port", "70000"], E, ("--port",)),
        Case("make-scenes into a non-empty folder", lambda ws: (notes(ws), ["make-scenes", str(ws), "--categories",
                                                                            "touching"])[1], E, (str("not empty"),)),
    ]
    # -- parameters
    c += [
        Case("--particles 0", lambda ws: estimate(ws, "--particles", "0"), E, ("particle count",)),
        Case("--iterations -1", lambda ws: estimate(ws, "--iterations", "-1"), E, ("iterations",)),
        Case("--workers 0", lambda ws: estimate(ws, "--workers", "0"), E, ("--workers",)),
        Case("--workers 1000", lambda ws: estimate(ws, "--workers", "1000"), E, ("--workers",)),
        Case("--seed -1", lambda ws: estimate(ws, "--seed", "-1"), E, ("seed",)),
        Case("--sigma-pos nan", lambda ws: estimate(ws, "--sigma-pos", "nan"), E, ("sigma",)),
        Case("--max-retries -1", lambda ws: estimate(ws, "--max-retries", "-1"), E, ("--max-retries",)),
        Case("--ray-address the dashboard URL", lambda ws: estimate(ws, "--engine", "ray", "--ray-address",
                                                                    "http://127.0.0.1:8265"), E, ("dashboard",)),
        Case("--ray-address http://[::1", lambda ws: estimate(ws, "--engine", "ray", "--ray-address", "http://[::1"),
             E, ("--ray-address",)),
        Case("--ray-address where nothing answers", lambda ws: estimate(ws, "--engine", "ray", "--ray-address",
                                                                        "127.0.0.1:1"), E, ("--ray-address",)),
        Case("--ray-address without --engine ray", lambda ws: estimate(ws, "--ray-address", "auto"), E,
             ("--ray-address",)),
    ]
    # -- runs that must recover (real estimates)
    c += [
        Case("a run into a new file", lambda ws: estimate(ws), "ok", writes=("r.csv",), slow=True),
        Case("a truncated collision-shape cache", lambda ws: damaged_cache(ws, "vhacd", "truncate"), "warn",
             ("vhacd", "damaged"), writes=("r.csv",), slow=True),
        Case("an emptied collision-shape cache", lambda ws: damaged_cache(ws, "vhacd", "empty"), "warn",
             ("vhacd", "damaged"), writes=("r.csv",), slow=True),
        Case("a killed evaluation worker", lambda ws: estimate(ws, "--workers", "2"), "warn",
             ("died", "started it again"), writes=("r.csv",), slow=True, during=kill_a_worker),
        Case("SIGTERM during a run", lambda ws: estimate(ws, "--workers", "2", "--particles", "64",
                                                         "--iterations", "30"), "sigterm",
             ("stopped by SIGTERM",), writes=("r.csv",), slow=True, during=terminate),
        # issue 34, item 6: 550 s without a line. The heartbeat speaks every 10 s; half a second for its jitter.
        Case("a 1.3M-face model, caches cold", heavy_model, "ok", ("simplifying obj_000006.ply (1.3M faces)",),
             writes=("r.csv",), slow=True, max_silence_s=10.0),
    ]
    return c


# ----------------------------------------------------------------------------------------------------------------
# Real-run helpers

CACHE = Path(tempfile.mkdtemp(prefix="hostile-cache-"))


def damaged_cache(ws: Path, kind: str, how: str) -> list[str]:
    """Fill the cache with a first run, then damage one of its files."""
    subprocess.run([*WORKBENCH, *estimate(ws, out="first.csv")], env=env_for(ws), capture_output=True, check=True)
    (ws / "first.csv").unlink()
    files = sorted((CACHE / "workbench" / kind).glob("*.npz"))
    if not files:
        raise RuntimeError(f"no {kind} cache files after a run")
    target = files[0]
    target.write_bytes(b"" if how == "empty" else target.read_bytes()[: target.stat().st_size // 2])
    return estimate(ws)


def children(pid: int) -> list[int]:
    try:
        return [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def kill_a_worker(proc: subprocess.Popen, ws: Path) -> None:
    """Once the run has its two workers and has been evaluating for a moment, kill one."""
    for _ in range(600):
        kids = [k for k in children(proc.pid) if "spawn_main" in _cmdline(k)]
        if len(kids) >= 2:
            time.sleep(2.0)
            os.kill(kids[0], signal.SIGKILL)
            return
        if proc.poll() is not None:
            return
        time.sleep(0.1)


def terminate(proc: subprocess.Popen, ws: Path) -> None:
    for _ in range(600):
        if len([k for k in children(proc.pid) if "spawn_main" in _cmdline(k)]) >= 2:
            time.sleep(3.0)
            proc.terminate()
            return
        if proc.poll() is not None:
            return
        time.sleep(0.1)


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    except OSError:
        return ""


def env_for(ws: Path) -> dict:
    return {**os.environ, "XDG_CACHE_HOME": str(CACHE), "WORKBENCH_HOME": str(ws / "home"),
            "PYTHONPATH": str(ROOT)}


# ----------------------------------------------------------------------------------------------------------------
# Running

def digests(folder: Path) -> dict[str, str]:
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file() and not p.name.startswith(".") and "home" not in p.relative_to(folder).parts:
            out[str(p.relative_to(folder))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def run_case(case: Case) -> tuple[bool, str]:
    with tempfile.TemporaryDirectory() as tmp:
        ws = Path(tmp)
        shutil.copytree(DEMO, ds(ws))
        holder = None
        try:
            try:
                argv = case.setup(ws)
            except Exception as err:  # noqa: BLE001 - a case that cannot be set up is not handled
                return False, f"set-up failed: {type(err).__name__}: {err}"
            if case.setup is locked:
                holder = subprocess.Popen(
                    [sys.executable, "-c", "import time; from workbench.io.outputs import OutputLock; "
                     f"OutputLock({str(ws / 'r.csv')!r}).acquire(); print('locked', flush=True); time.sleep(120)"],
                    stdout=subprocess.PIPE, text=True, env=env_for(ws))
                holder.stdout.readline()
            before = digests(ws)
            proc = subprocess.Popen([*WORKBENCH, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                    env=env_for(ws), cwd=ws)
            helper = None
            if case.during is not None:
                helper = threading.Thread(target=case.during, args=(proc, ws))
                helper.start()
            silence = None
            if case.max_silence_s is not None:
                err, silence = timed_stderr(proc, 600)
            else:
                try:
                    _, err = proc.communicate(timeout=600)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    return False, "timed out"
            if helper is not None:
                helper.join()
        finally:
            if holder is not None:
                holder.kill()
                holder.wait()
            for p in ws.rglob("*"):
                if p.is_dir():
                    p.chmod(0o755)
        after = digests(ws)
        changed = sorted(k for k in set(before) | set(after)
                         if before.get(k) != after.get(k) and k not in case.writes)
        problems = []
        if "Traceback" in err:
            problems.append("traceback")
        if changed:
            problems.append(f"changed {changed[:3]}")
        rc = proc.returncode
        if case.expect == "error":
            if rc != 2 or not err.startswith("workbench: error: "):
                problems.append(f"exit {rc}, stderr {err.strip()[-200:]!r}")
        elif case.expect == "sigterm":
            if rc != 143:
                problems.append(f"exit {rc}")
        elif rc != 0:
            problems.append(f"exit {rc}, stderr {err.strip()[-200:]!r}")
        for w in case.words:
            if w not in err:
                problems.append(f"no {w!r} in {err.strip()[-200:]!r}")
        if silence is not None and silence > case.max_silence_s:
            problems.append(f"{silence:.1f} s without a line on stderr")
        first = next((line for line in err.splitlines() if line.startswith(("workbench", "WARNING"))), "")
        if silence is not None:
            first = f"{first[:100]} (longest silence {silence:.1f} s)"
        return not problems, "; ".join(problems) or first[:150]


def timed_stderr(proc: subprocess.Popen, timeout: float) -> tuple[str, float]:
    """``proc``'s stderr to its end, and the longest time it went without a line, from the start to the exit
    (killed after ``timeout`` seconds)."""
    killer = threading.Timer(timeout, proc.kill)
    killer.start()
    t0 = last = time.monotonic()
    longest, lines = 0.0, []
    try:
        for line in proc.stderr:
            now = time.monotonic()
            longest, last = max(longest, now - last), now
            lines.append(line)
        proc.wait()
        proc.stdout.read()
    finally:
        killer.cancel()
    longest = max(longest, time.monotonic() - last)
    if time.monotonic() - t0 >= timeout:
        lines.append("timed out\n")
    return "".join(lines), longest


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="skip the cases that run a real estimate")
    parser.add_argument("--only", default=None, help="run only the cases whose name holds this")
    parser.add_argument("--slow-only", action="store_true", help="run only the cases that run a real estimate")
    args = parser.parse_args()
    todo = [c for c in cases() if not (args.quick and c.slow) and (c.slow or not args.slow_only)
            and (args.only is None or args.only in c.name)]
    handled = 0
    t0 = time.perf_counter()
    for n, case in enumerate(todo, 1):
        ok, note = run_case(case)
        handled += ok
        print(f"{n:3d} {'ok ' if ok else 'BAD'} {case.name}: {note}", flush=True)
    print(f"{handled} of {len(todo)} handled ({time.perf_counter() - t0:.0f} s)")
    shutil.rmtree(CACHE, ignore_errors=True)
    return 0 if handled == len(todo) else 1


if __name__ == "__main__":
    sys.exit(main())
