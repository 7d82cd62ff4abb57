"""Hostile cases, tried as a new user would: the command line run as a subprocess on a fresh copy of the demo
dataset (assets/demo) per case, with damaged inputs, outputs that must not be written, concurrent runs, damaged
caches, a killed worker, bad parameters. Prints one line per case and "N of M handled".

A case is *handled* when the command ends as expected, with no traceback on stderr:
- ``error``: exit code 2 and ``workbench: error: FILE: problem``, naming what the case names;
- ``ok`` / ``warn``: exit code 0 (``warn``: with a WARNING naming what the case names);
and, whatever the outcome, every file the user had (the dataset copy, their notes, their results) is left as it
was, except the output the case allows to be written.

    .venv/bin/python benchmarks/hostile_cases.py [--quick] [--only WORD] [--jobs N]

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
import itertools
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
    file_bytes: int | None = None  # the most bytes the command may write to any file (RLIMIT_FSIZE): a full disk


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
    return c + issue67_cases()


# ----------------------------------------------------------------------------------------------------------------
# Issue 67: a hostile run of the newer parts (track, --posterior, score, sessions, serve, resource abuse)

DEEP = 200_000
# What a JSON input may be damaged to -> (its bytes, words the error must hold besides the file's name).
JSON_DAMAGES = {
    f"nested {DEEP:,} levels": (('{"0": ' + "[" * DEEP + "]" * DEEP + "}").encode(), "nested deeper"),
    "nested 100 levels": (('{"0": ' + "[" * 100 + "]" * 100 + "}").encode(), "more than 64 levels"),
    "a 400-digit integer": (('{"0": [' + "9" * 400 + "]}").encode(), "number of 400 characters"),
    "a 5000-digit integer": (('{"0": [' + "9" * 5000 + "]}").encode(), "number of 5000 characters"),
    "a 5000-digit fraction": (('{"0": [0.' + "1" * 5000 + "]}").encode(), "number of 5002 characters"),
    "not UTF-8": (b'{"0": "\xff\xfe"}', "corrupt"),
    "empty": (b"", "corrupt"),
    "cut short": (b'{"0": [1, ', "corrupt"),
    "binary": (bytes(range(256)), "corrupt"),
    "null": (b"null", ""),
    "a number": (b"42", ""),
    "a string": (b'"scene"', ""),
}


def damaged_json(rel: str, data: bytes, then: Callable[[Path], list[str]]):
    def setup(ws: Path) -> list[str]:
        argv = then(ws)  # first: a set-up may write the file that is then damaged
        p = ws / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
        return argv
    return setup


def scored(ws: Path, *rows: str, extra: tuple[str, ...] = ()) -> list[str]:
    results(ws, *(rows or (ROW,)))
    return ["score", str(ds(ws)), str(ws / "r.csv"), *extra]


def world(ws: Path, t_of: Callable[[int], list[float]] = lambda i: [10.0 * i, 0.0, 900.0]) -> Path:
    """scene_camera_world.json for the demo's frames (a slow turn, translations from ``t_of``)."""
    import math

    poses = {}
    for i in sorted(int(k) for k in json.loads((scene(ws) / "scene_camera.json").read_text())):
        a = 0.05 * i
        R = [math.cos(a), -math.sin(a), 0.0, math.sin(a), math.cos(a), 0.0, 0.0, 0.0, 1.0]
        poses[str(i)] = {"R_w2c": R, "t_w2c": t_of(i)}
    p = scene(ws) / "scene_camera_world.json"
    p.write_text(json.dumps(poses))
    return p


def track(ws: Path, *extra: str, out: str = "r.csv") -> list[str]:
    return ["track", str(ds(ws)), "--scene", "0", *TINY, "--track-particles", "8", "--track-iterations", "1",
            "--out", str(ws / out), *extra]


def sequence(n: int, change: Callable[[Path], None] | None = None, *extra: str):
    """The demo's frame 0 copied to frames 1..n-1 (a still camera), ``change`` applied, then ``track``."""
    def setup(ws: Path) -> list[str]:
        for name in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
            edit_json(scene(ws) / name, lambda d: {str(i): d["0"] for i in range(n)})
        for i in range(1, n):
            shutil.copy(depth_png(ws), scene(ws) / "depth" / f"{i:06d}.png")
        if change is not None:
            change(ws)
        return track(ws, *extra)
    return setup


def depth_of(i: int, data: bytes | Callable[[Path], bytes]):
    def change(ws: Path) -> None:
        p = scene(ws) / "depth" / f"{i:06d}.png"
        p.write_bytes(data(p) if callable(data) else data)
    return change


def scaled_depth(factor: float):
    """The depth PNG's readings times ``factor`` (clipped to 16 bits)."""
    def data(p: Path) -> bytes:
        raw = np.asarray(Image.open(p)).astype(np.float64) * factor
        return png(np.clip(np.round(raw), 0, 65535).astype(np.uint16))
    return data


def png_header(width: int, height: int) -> bytes:
    """A 16-bit PNG whose header says ``width`` x ``height``: the reader must refuse it from the header alone."""
    data = bytearray(png(np.full((2, 2), 1000, np.uint16)))
    data[16:24] = width.to_bytes(4, "big") + height.to_bytes(4, "big")
    return bytes(data)


def bad_crc(ws: Path) -> bytes:
    data = bytearray(depth_png(ws).read_bytes())
    data[len(data) // 2] ^= 0xFF  # a byte of the compressed pixels
    return bytes(data)


def inside_out(ws: Path) -> list[str]:
    import trimesh

    ply = ds(ws) / "models" / "obj_000005.ply"
    mesh = trimesh.load(ply, process=False)
    mesh.invert()
    mesh.export(ply)
    return scored(ws)


def session_file(ws: Path) -> Path:
    return ws / "sessions" / "s.json"


def issue67_cases() -> list[Case]:
    c: list[Case] = []
    E = "error"
    # -- the one JSON reader: every JSON input, each damage (the file's name and the problem in the message)
    inputs = {
        "scene_camera.json": ("demo/test/000000/scene_camera.json", estimate),
        "scene_gt.json": ("demo/test/000000/scene_gt.json", estimate),
        "models_info.json": ("demo/models/models_info.json", estimate),
        "camera.json": ("demo/camera.json", estimate),
        "scene_gt_info.json (score)": ("demo/test/000000/scene_gt_info.json", scored),
        "scenes.json (score)": ("demo/scenes.json", scored),
        "scene_camera_world.json (track)": ("demo/test/000000/scene_camera_world.json", track),
        "a session (serve)": ("sessions/s.json", lambda ws: ["serve", "--session", str(session_file(ws))]),
    }
    for label, (rel, command) in inputs.items():
        for damage, (data, words) in JSON_DAMAGES.items():
            c.append(Case(f"{label}: {damage}", damaged_json(rel, data, command), E,
                          (Path(rel).name, *((words,) if words else ()))))
    c += [
        Case("score --json over a file nested 200,000 levels", lambda ws: (
            (ws / "s.json").write_bytes(JSON_DAMAGES[f"nested {DEEP:,} levels"][0]),
            scored(ws, extra=("--json", str(ws / "s.json"))))[1], E, ("s.json", "--force")),
        Case("score --json over a 5000-digit number", lambda ws: (
            (ws / "s.json").write_bytes(JSON_DAMAGES["a 5000-digit integer"][0]),
            scored(ws, extra=("--json", str(ws / "s.json"))))[1], E, ("s.json", "--force")),
        Case("--posterior --resume on a file nested 200,000 levels", lambda ws: (
            results(ws, ROW), (ws / "p.json").write_bytes(JSON_DAMAGES[f"nested {DEEP:,} levels"][0]),
            ["estimate", str(ds(ws)), "--particles", "16", "--iterations", "1", "--resume", "--posterior",
             str(ws / "p.json"), "--out", str(ws / "r.csv")])[2], E, ("p.json",)),
    ]
    # -- the one image reader: the depth image's limits and damages
    d = "demo/test/000000/depth/000000.png"
    c += [
        Case("depth 20000 x 20000 (PIL's bomb error)", write(d, png_header(20000, 20000)), E,
             ("000000.png", "20000 x 20000 pixels")),
        Case("depth 13000 x 13000 (PIL's bomb warning)", write(d, png_header(13000, 13000)), E,
             ("000000.png", "13000 x 13000 pixels")),
        Case("depth 5001 x 5001", write(d, png_header(5001, 5001)), E, ("000000.png", "5001 x 5001 pixels")),
        Case("depth 100000 x 1", write(d, png_header(100000, 1)), E, ("000000.png",)),
        Case("depth 1 x 1", write(d, png(np.full((1, 1), 1000, np.uint16))), E, ("000000.png",)),
        Case("depth of 640 x 1", write(d, png(np.full((1, 640), 1000, np.uint16))), E, ("000000.png",)),
        Case("depth 8-bit grey", write(d, png(np.full((480, 640), 100, np.uint8))), E, ("000000.png", "16-bit")),
        Case("depth RGBA", write(d, png(np.full((480, 640, 4), 100, np.uint8))), E, ("000000.png", "16-bit")),
        Case("depth a JPEG named .png", lambda ws: (Image.fromarray(np.zeros((480, 640, 3), np.uint8)).save(
            depth_png(ws), format="JPEG"), estimate(ws))[1], E, ("000000.png",)),
        Case("depth a text file", write(d, "depth goes here\n"), E, ("000000.png", "corrupt")),
        Case("depth with a damaged pixel stream", lambda ws: (depth_png(ws).write_bytes(bad_crc(ws)),
                                                              estimate(ws))[1], E, ("000000.png",)),
        Case("depth saturated (65535 everywhere)", write(d, png(np.full((480, 640), 65535, np.uint16))), E,
             ("depth_scale",)),
        Case("depth 1000x too small", lambda ws: (depth_png(ws).write_bytes(scaled_depth(1e-3)(depth_png(ws))),
                                                   estimate(ws))[1], E, ("depth_scale",)),
        Case("depth a folder", lambda ws: (depth_png(ws).unlink(), depth_png(ws).mkdir(), estimate(ws))[2], E,
             ("000000.png",)),
    ]
    # -- score: rows that are no estimates, or no probabilities
    R = "1 0 0 0 1 0 0 0 1"
    c += [
        Case("score: a NaN score", lambda ws: scored(ws, f"0,0,5,nan,{R},0 0 500,1.0"), E, ("r.csv", "line 2")),
        Case("score: an inf score", lambda ws: scored(ws, f"0,0,5,inf,{R},0 0 500,1.0"), E, ("r.csv", "line 2")),
        Case("score: a -inf score", lambda ws: scored(ws, f"0,0,5,-inf,{R},0 0 500,1.0"), E, ("r.csv", "line 2")),
        Case("score: a NaN score beside a mode (no RuntimeWarning)", lambda ws: scored(
            ws, f"0,0,5,nan,{R},0 0 500,1.0", f"0,0,5,0.5,{R},0 0 510,1.0"), E, ("line 2",)),
        Case("score: a NaN time", lambda ws: scored(ws, f"0,0,5,1,{R},0 0 500,nan"), E, ("r.csv", "line 2")),
        Case("score: a row repeated", lambda ws: scored(ws, ROW, ROW), E, ("line 3 repeats line 2",)),
        Case("score: modes summing to 1.8", lambda ws: scored(ws, f"0,0,5,0.9,{R},0 0 500,1.0",
                                                              f"0,0,5,0.9,{R},0 0 510,1.0"), E, ("sum to 1.8",)),
        Case("score: modes of -1 and 2", lambda ws: scored(ws, f"0,0,5,-1,{R},0 0 500,1.0",
                                                           f"0,0,5,2,{R},0 0 510,1.0"), E, ("probabilities",)),
        Case("score: modes summing to 1", lambda ws: scored(ws, f"0,0,5,0.6,{R},0 0 500,1.0",
                                                            f"0,0,5,0.4,{R},0 0 510,1.0"), "ok"),
        Case("score: not UTF-8", lambda ws: ((ws / "r.csv").write_bytes(HEADER.encode() + b"\n\xff\xfe\n"),
                                             ["score", str(ds(ws)), str(ws / "r.csv")])[1], E, ("UTF-8",)),
        Case("score: a 400-digit translation", lambda ws: scored(ws, f"0,0,5,1,{R},0 0 5{'0' * 400},1.0"), E,
             ("line 2",)),
        Case("score: a 5000-digit object id", lambda ws: scored(ws, f"0,0,5{'0' * 5000},1,{R},0 0 500,1.0"), E,
             ("line 2",)),
        Case("score: an extra column", lambda ws: scored(ws, ROW + ",x"), E, ("line 2",)),
        Case("score: a missing column", lambda ws: scored(ws, ROW.rsplit(",", 1)[0]), E, ("line 2",)),
        Case("score: the header alone", lambda ws: (results(ws), ["score", str(ds(ws)), str(ws / "r.csv")])[1],
             "ok"),
        Case("score: a folder as the results", lambda ws: ["score", str(ds(ws)), str(ws)], E, ()),
        Case("score: --reliability a folder", lambda ws: scored(ws, extra=("--reliability", str(ws))), E,
             ("is a folder",)),
    ]
    # -- count options: upper bounds with their reasons, memory checked before the run
    huge = ("--max-render-pixels", "1000000")  # with 100000 particles: ~1.3 TB by the measured rate
    c += [
        Case("--iterations 100000", lambda ws: estimate(ws, "--iterations", "100000"), E, ("--iterations", "10000")),
        Case("--iterations 10001", lambda ws: estimate(ws, "--iterations", "10001"), E, ("--iterations",)),
        Case("--particles 100001", lambda ws: estimate(ws, "--particles", "100001"), E, ("100000",)),
        Case("--particles 100000 at 1M render pixels", lambda ws: estimate(ws, "--particles", "100000", *huge), E,
             ("--particles", "GiB")),
        Case("--max-render-pixels 100000000", lambda ws: estimate(ws, "--max-render-pixels", "100000000"), E,
             ("--max-render-pixels",)),
        Case("--max-render-pixels 10", lambda ws: estimate(ws, "--max-render-pixels", "10"), E,
             ("--max-render-pixels",)),
        Case("--max-retries 1000", lambda ws: estimate(ws, "--max-retries", "1000"), E, ("--max-retries", "100")),
        Case("--workers 1000000", lambda ws: estimate(ws, "--workers", "1000000"), E, ("--workers",)),
        Case("--seed 2**64", lambda ws: estimate(ws, "--seed", str(2**64)), E, ("seed",)),
        Case("--sigma-deg inf", lambda ws: estimate(ws, "--sigma-deg", "inf"), E, ("sigma",)),
        Case("--floor-from 2", lambda ws: estimate(ws, "--floor-from", "2"), E, ("floor_from",)),
        Case("track --track-particles 10000000", lambda ws: track(ws, "--track-particles", "10000000"), E,
             ("--track-particles",)),
        Case("track --track-particles 100000 at 1M render pixels",
             lambda ws: track(ws, "--track-particles", "100000", *huge), E, ("--track-particles", "GiB")),
        Case("track --track-iterations 100000", lambda ws: track(ws, "--track-iterations", "100000"), E,
             ("--track-iterations", "1000")),
        Case("track --track-particles 0", lambda ws: track(ws, "--track-particles", "0"), E, ("--track-particles",)),
        Case("track --track-iterations 0", lambda ws: track(ws, "--track-iterations", "0"), E,
             ("--track-iterations",)),
        Case("track --particles 100000 at 1M render pixels", lambda ws: track(ws, "--particles", "100000", *huge),
             E, ("--particles", "GiB")),
        Case("track --max-retries 101", lambda ws: track(ws, "--max-retries", "101"), E, ("--max-retries",)),
        Case("serve --particles 10000000", lambda ws: ["serve", "--demo", "--particles", "10000000"], E,
             ("--particles",)),
        Case("serve --iterations 100000", lambda ws: ["serve", "--demo", "--iterations", "100000"], E,
             ("--iterations",)),
        Case("bench --repeats 0", lambda ws: ["bench", "--speed", "--repeats", "0"], E, ("--repeats",)),
        Case("bench --repeats 1000000", lambda ws: ["bench", "--speed", "--repeats", "1000000"], E, ("--repeats",)),
        Case("bench --per-category 1000000", lambda ws: ["bench", str(ds(ws)), "--per-category", "1000000"], E,
             ("--per-category",)),
        Case("make-scenes --per-category 1000000", lambda ws: ["make-scenes", str(ws / "m"), "--per-category",
                                                               "1000000"], E, ("--per-category",)),
        Case("make-scenes --sequence 1000000", lambda ws: ["make-scenes", str(ws / "m"), "--sequence", "1000000"],
             E, ("--sequence",)),
        Case("make-scenes --sequence 0", lambda ws: ["make-scenes", str(ws / "m"), "--sequence", "0"], E,
             ("--sequence",)),
    ]
    # -- outputs: a file that would never be written, a lock on a full disk
    c += [
        Case("--posterior with --no-settle", lambda ws: estimate(ws, "--posterior", str(ws / "p.json")), E,
             ("--posterior", "--no-settle")),
        Case("--posterior with --proposals paper", lambda ws: ["estimate", str(ds(ws)), "--proposals", "paper",
                                                                "--posterior", str(ws / "p.json"), "--out",
                                                                str(ws / "r.csv")], E, ("--proposals paper",)),
        Case("track --posterior with --no-settle", lambda ws: track(ws, "--posterior", str(ws / "p.json")), E,
             ("--posterior", "--no-settle")),
        Case("--posterior the same file as --out", lambda ws: estimate(ws, "--posterior", str(ws / "r.csv")), E,
             ("--posterior",)),
        Case("--posterior a folder", lambda ws: ["estimate", str(ds(ws)), "--posterior", str(ws), "--out",
                                                 str(ws / "r.csv")], E, ("is a folder",)),
        Case("--posterior in the dataset", lambda ws: ["estimate", str(ds(ws)), "--posterior",
                                                       str(scene(ws) / "p.json"), "--out", str(ws / "r.csv")], E,
             ("dataset folder",)),
        Case("--posterior over a user's notes", lambda ws: (notes(ws), ["estimate", str(ds(ws)), "--posterior",
                                                                        str(ws / "notes.txt"), "--out",
                                                                        str(ws / "r.csv")])[1], E, ("--force",)),
        Case("a full disk while taking the --out lock", lambda ws: estimate(ws), E, ("lock file", "r.csv"),
             file_bytes=0),
        Case("a full disk while taking the track --out lock", lambda ws: track(ws), E, ("lock file", "r.csv"),
             file_bytes=0),
        Case("track --out a folder", lambda ws: track(ws, out="."), E, ("is a folder",)),
        Case("track --out a user's notes", lambda ws: (notes(ws), track(ws, out="notes.txt"))[1], E, ("--force",)),
    ]
    # -- track: every frame checked before the first runs, naming the frame and its file
    c += [
        Case("track: frame 2 of 320 x 240", sequence(3, depth_of(2, png(np.full((240, 320), 8000, np.uint16)))),
             E, ("000002.png", "frame 2", "320x240")),
        Case("track: frame 1 saturated", sequence(3, depth_of(1, png(np.full((480, 640), 65535, np.uint16)))), E,
             ("000001.png", "frame 1", "saturated")),
        Case("track: frame 2 1000x smaller", sequence(3, depth_of(2, scaled_depth(1e-3))), E,
             ("000002.png", "frame 2", "another scale")),
        Case("track: frame 2 20x smaller", sequence(3, depth_of(2, scaled_depth(0.05))), E,
             ("000002.png", "frame 2", "another scale")),
        Case("track: frame 2 all zeros", sequence(3, depth_of(2, png(np.zeros((480, 640), np.uint16)))), E,
             ("000002.png", "no valid pixel")),
        Case("track: frame 2 20000 x 20000", sequence(3, depth_of(2, png_header(20000, 20000))), E,
             ("000002.png", "20000 x 20000")),
        Case("track: frame 2 not a PNG", sequence(3, depth_of(2, b"not a png")), E, ("000002.png",)),
        Case("track: frame 1's depth missing", sequence(3, lambda ws: (scene(ws) / "depth" / "000001.png").unlink()),
             E, ("000001.png",)),
        Case("track: --frames 2:1", sequence(3, None, "--frames", "2:1"), E, ("--frames",)),
        Case("track: --frames x", sequence(3, None, "--frames", "x"), E, ("--frames",)),
        Case("track: --frames 0:9", sequence(3, None, "--frames", "0:9"), E, ("no frame 9",)),
        Case("track: --scene 99", lambda ws: ["track", str(ds(ws)), "--scene", "99", "--out", str(ws / "r.csv")], E,
             ("99",)),
        Case("track: --motion given without a world file", lambda ws: track(ws, "--motion", "given"), E,
             ("scene_camera_world.json",)),
        Case("track: a world pose missing", sequence(3, lambda ws: edit_json(world(ws), lambda d: (d.pop("1"),
                                                                                                None)[1])), E,
             ("scene_camera_world.json", "frame 1")),
        Case("track: a world pose a reflection", sequence(2, lambda ws: edit_json(
            world(ws), lambda d: d["1"].__setitem__("R_w2c", [-1, 0, 0, 0, 1, 0, 0, 0, 1]))), E,
             ("scene_camera_world.json",)),
        Case("track: t_w2c in micrometres", sequence(3, lambda ws: world(ws, lambda i: [1e4 * i, 0.0, 9e5])),
             "warn", ("scene_camera_world.json", "micrometres"), writes=("r.csv",), slow=True),
        Case("track: t_w2c in metres", sequence(3, lambda ws: world(ws, lambda i: [0.01 * i, 0.0, 0.9])), "warn",
             ("scene_camera_world.json", "metres"), writes=("r.csv",), slow=True),
    ]
    # -- serve
    c += [
        Case("serve --frame 99", lambda ws: ["serve", str(ds(ws)), "--frame", "99"], E, ("frame 99", "scene 0")),
        Case("serve --scene 99", lambda ws: ["serve", str(ds(ws)), "--scene", "99"], E, ("scene 99",)),
        Case("serve --scene 0 --frame 99", lambda ws: ["serve", str(ds(ws)), "--scene", "0", "--frame", "99"], E,
             ("frame 99", "scene 0")),
        Case("serve --port 0", lambda ws: ["serve", "--demo", "--port", "0"], E, ("--port",)),
        Case("serve --host 0.0.0.0, then SIGTERM", lambda ws: ["serve", "--demo", "--host", "0.0.0.0", "--port",
                                                                "18393", "--sessions-dir", str(ws / "s")], "sigterm",
             ("WARNING: serving on 0.0.0.0", "labels", "sessions"), slow=True, during=terminate_when_serving),
        Case("serve, then SIGTERM", lambda ws: ["serve", "--demo", "--port", "18394", "--sessions-dir",
                                                str(ws / "s")], "sigterm", (), slow=True,
             during=terminate_when_serving),
    ]
    # -- meshes, Ray
    c += [
        Case("a mesh wound inside out", inside_out, "warn", ("obj_000005.ply", "inside out")),
        Case("--engine ray with RAY_ADDRESS naming another cluster", lambda ws: estimate(ws, "--engine", "ray"),
             "ok", writes=("r.csv",), slow=True, env={"RAY_ADDRESS": "127.0.0.1:1"}),
    ]
    return c


def terminate_when_serving(proc: subprocess.Popen, ws: Path) -> None:
    """SIGTERM once the server has started its evaluation workers and their number held for 3 s (a worker stopped
    while Python's spawn still reads its start-up data prints that module's traceback: not what the case asks)."""
    last, since = -1, time.monotonic()
    for _ in range(1200):
        if proc.poll() is not None:
            return
        now = len([k for k in children(proc.pid) if "spawn_main" in _cmdline(k)])
        if now != last:
            last, since = now, time.monotonic()
        elif now > 0 and time.monotonic() - since >= 3.0:
            proc.terminate()
            return
        time.sleep(0.25)


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
                                    env={**env_for(ws), **case.env}, cwd=ws,
                                    preexec_fn=None if case.file_bytes is None else limit_files(case.file_bytes))
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


def limit_files(most: int) -> Callable[[], None]:
    """For ``preexec_fn``: the command may write at most ``most`` bytes to any file, and a write beyond fails with
    EFBIG (SIGXFSZ ignored) as a write to a full disk fails with ENOSPC."""
    def limit() -> None:
        import resource

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (most, most))
    return limit


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
    parser.add_argument("--jobs", type=int, default=1,
                        help="quick cases run side by side (each in its own copy of the demo); the cases that run a "
                             "real estimate share a cache and one at a time (default 1)")
    args = parser.parse_args()
    todo = [c for c in cases() if not (args.quick and c.slow) and (c.slow or not args.slow_only)
            and (args.only is None or args.only in c.name)]
    todo = [c for c in todo if not c.slow] + [c for c in todo if c.slow]
    handled = 0
    t0 = time.perf_counter()
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        quick = pool.map(run_case, [c for c in todo if not c.slow])  # in order, as each is done
        outcomes = itertools.chain(quick, (run_case(c) for c in todo if c.slow))
        for n, (case, (ok, note)) in enumerate(zip(todo, outcomes), 1):
            handled += ok
            print(f"{n:3d} {'ok ' if ok else 'BAD'} {case.name}: {note}", flush=True)
    print(f"{handled} of {len(todo)} handled ({time.perf_counter() - t0:.0f} s)")
    shutil.rmtree(CACHE, ignore_errors=True)
    return 0 if handled == len(todo) else 1


if __name__ == "__main__":
    sys.exit(main())
