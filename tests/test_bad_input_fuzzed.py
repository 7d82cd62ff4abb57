"""Hostile input, generated. Every field of the demo dataset's JSON files, its depth image, and a saved session's
files are mutated: type swaps, missing keys, truncated lists and files, extreme numbers. Every case must end in
success or ``InputError`` (the command line's ``workbench: error: FILE: problem``, exit code 2), never any other
exception, and must leave every input file as it was.

Most cases run in this process, through what the command line runs: the dataset's frames are loaded into
problems and, for each distinct problem, a small estimate is run; a session is loaded, its problem rebuilt and
one step taken. A sample of the cases runs the real command line as a subprocess. Run this file with ``-s`` to
see how many cases were tried."""

from __future__ import annotations

import hashlib
import io
import json
import math
import shutil
import subprocess
import sys
import traceback
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from workbench.app.engine.engine import DEMO_DIR
from workbench.errors import InputError
from workbench.evaluation import LocalEvaluator
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator
from workbench.io import bop
from workbench.problem.build import load_bop_problem
from workbench.score import gt_info
from workbench.sessions import store as sessions

pytestmark = pytest.mark.slow  # needs whole estimates: pybullet and OpenGL

SWAPS = ["abc", None, True, [], {}]
NUMBERS = [0, -1, 1e308, -1e308, 10**30, math.nan]
CLI_SAMPLE = 12  # dataset cases run as a subprocess too (about 2 s each)


# ----------------------------------------------------------------------------------------------------------------
# Mutations


def _children(value):
    """The keys or indices fuzzed below a JSON value: every key; of a list, the first and last entries (the
    entries of one list have one type: the ends stand for the rest)."""
    if isinstance(value, dict):
        return list(value)
    if isinstance(value, list):
        return sorted({0, len(value) - 1}) if value else []
    return []


def _nodes(value, path=()):
    """Paths (tuples of keys and indices) to every fuzzed node below the root."""
    for key in _children(value):
        yield path + (key,)
        yield from _nodes(value[key], path + (key,))


def _replaced(doc, path, new=..., delete=False):
    doc = json.loads(json.dumps(doc))
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    if delete:
        del parent[path[-1]]
    else:
        parent[path[-1]] = new
    return doc


def json_mutations(text: str):
    """(description, new file text) for every mutation of a JSON file."""
    doc = json.loads(text)
    yield "truncated file", text[: len(text) // 2]
    yield "empty file", ""
    yield "a list instead of an object", "[]"
    for path in _nodes(doc):
        where = "/".join(map(str, path))
        value = _value(doc, path)
        if isinstance(_value(doc, path[:-1]), dict):
            yield f"{where} missing", json.dumps(_replaced(doc, path, delete=True))
        for new in SWAPS + NUMBERS:
            if type(new) is not type(value) or new != value:  # NaN != NaN: a NaN value is replaced by NaN, harmless
                yield f"{where} = {json.dumps(new)[:20]}", json.dumps(_replaced(doc, path, new))
        if isinstance(value, list) and value:
            yield f"{where} truncated", json.dumps(_replaced(doc, path, value[:-1]))


def _value(doc, path):
    for key in path:
        doc = doc[key]
    return doc


def _png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def depth_mutations(data: bytes):
    """(description, new file bytes) for a 16-bit depth PNG."""
    depth = np.asarray(Image.open(io.BytesIO(data))).astype(np.uint16)
    rng = np.random.default_rng(0)
    one = np.zeros_like(depth)
    one[depth.shape[0] // 2, depth.shape[1] // 2] = depth[depth > 0][0]
    yield "truncated file", data[: len(data) // 2]
    yield "empty file", b""
    yield "not an image", b"depth" * 100
    yield "8-bit", _png((depth // 256).astype(np.uint8))
    yield "colour", _png(np.repeat((depth // 256).astype(np.uint8)[..., None], 3, axis=2))
    yield "all zero", _png(np.zeros_like(depth))
    yield "one valid pixel", _png(one)
    yield "all at the maximum", _png(np.full_like(depth, 65535))
    yield "noise", _png(rng.integers(1, 65535, depth.shape).astype(np.uint16))
    yield "half size", _png(depth[::2, ::2].copy())
    yield "1x1", _png(depth[:1, :1].copy())
    yield "transposed", _png(depth.T.copy())
    yield "depth x 10", _png(np.minimum(depth.astype(np.uint32) * 10, 65535).astype(np.uint16))
    yield "depth / 10", _png((depth // 10).astype(np.uint16))


# ----------------------------------------------------------------------------------------------------------------
# Running a case


def _digests(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


class Runs:
    """Small estimates, one per distinct problem (most mutations leave the problem as it was); evaluators are
    reused for problems with equal fingerprints (same observation, table, render grid)."""

    def __init__(self):
        self.done: set = set()
        self.evaluators: dict[str, LocalEvaluator] = {}

    def evaluator(self, problem) -> LocalEvaluator:
        key = sessions.problem_fingerprint(problem)
        if key not in self.evaluators:
            if len(self.evaluators) > 1:  # keep the baseline's and the latest: each holds a GL context
                last = list(self.evaluators)[-1]
                self.evaluators.pop(last).close()
            self.evaluators[key] = LocalEvaluator(problem)
        return self.evaluators[key]

    def estimate(self, problem) -> None:
        key = (sessions.problem_fingerprint(problem),
               tuple(m.symmetries.tobytes() for m in problem.models), tuple(m.obj_id for m in problem.models))
        if key in self.done:
            return
        estimator = Estimator(problem, EstimatorConfig(particles=6, iterations=2, seed=0), self.evaluator(problem))
        estimator.run(stop_on_convergence=False)
        self.done.add(key)

    def close(self) -> None:
        for ev in self.evaluators.values():
            ev.close()


def run_dataset(dataset: Path, runs: Runs) -> None:
    """What ``estimate`` (and ``bench``, for scenes.json and scene_gt_info.json) reads, then a small estimate."""
    for scene_id, im_id in bop.list_frames(dataset):
        frame, problem = load_bop_problem(dataset, scene_id, im_id)
        gt_info.visib_fractions(frame)
        runs.estimate(problem)
    gt_info.scene_categories(dataset)


def run_session(path: Path, runs: Runs, problems: dict) -> None:
    """What the app does with a session: load, check the dataset, rebuild the problem, continue one step."""
    state = sessions.load_session(path)
    sessions.check_dataset(state)
    key = repr((state.frame, state.T_cam_world.tobytes(), state.table, state.problem_config))
    if key not in problems:
        problems[key] = sessions.session_problem(state)[1]
    problem = problems[key]
    estimator = sessions.restore_estimator(state, problem, runs.evaluator(problem))
    estimator.step()


def outcome(action) -> str:
    """'ok', 'error' (InputError) or 'CRASH ...' with the traceback."""
    try:
        action()
    except InputError as err:
        assert err.problem, "an InputError without a problem"
        return "error"
    except Exception:  # noqa: BLE001 - exactly what the fuzz looks for
        return "CRASH\n" + traceback.format_exc()
    return "ok"


def _workbench(*args):
    return subprocess.run([sys.executable, "-m", "workbench.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


# ----------------------------------------------------------------------------------------------------------------
# The test


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fuzz") / "demo"
    shutil.copytree(DEMO_DIR, out)
    return out


@pytest.fixture(scope="module")
def saved_session(demo, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("sessions")
    frame, problem = load_bop_problem(demo, 0, 0)
    ev = LocalEvaluator(problem)
    try:
        est = Estimator(problem, EstimatorConfig(particles=6, iterations=10, seed=1), ev)
        est.step(), est.step()
        ref = sessions.frame_ref_for(demo, frame, problem)
        state = sessions.session_state_from(est, ref, [est.estimate[0], None])
        return sessions.save_session(folder, "fuzz", state)
    finally:
        ev.close()


def test_every_mutated_input_ends_in_success_or_a_clear_error(demo, saved_session, tmp_path):
    runs = Runs()
    problems: dict = {}
    crashes, changed, counts = [], [], {"ok": 0, "error": 0}
    cases = []  # (file, description, content) of the dataset, for the command-line sample
    try:
        assert outcome(lambda: run_dataset(demo, runs)) == "ok"  # the unmutated demo works
        targets = [(p, json_mutations(p.read_text())) for p in sorted(demo.rglob("*.json"))]
        targets.append((demo / "test" / "000000" / "depth" / "000000.png",
                        depth_mutations((demo / "test" / "000000" / "depth" / "000000.png").read_bytes())))
        session_files = [saved_session, *saved_session.parent.glob("*.npz")]
        npz = session_files[1]
        targets.append((saved_session, json_mutations(saved_session.read_text())))
        npz_bytes = npz.read_bytes()
        flipped = npz_bytes[:100] + bytes([npz_bytes[100] ^ 1]) + npz_bytes[101:]
        targets.append((npz, iter([("truncated", npz_bytes[: len(npz_bytes) // 2]), ("empty", b""),
                                   ("one byte changed", flipped)])))
        for path, mutations in targets:
            original = path.read_bytes()
            is_session = path in session_files
            folder = saved_session.parent if is_session else demo
            for description, content in mutations:
                path.write_bytes(content.encode() if isinstance(content, str) else content)
                before = _digests(folder)
                if is_session:
                    result = outcome(lambda: run_session(saved_session, runs, problems))
                else:
                    result = outcome(lambda: run_dataset(demo, runs))
                    cases.append((path, description, content, result))
                name = f"{path.name}: {description}"
                if result.startswith("CRASH"):
                    crashes.append(f"{name}\n{result}")
                else:
                    counts[result] += 1
                if _digests(folder) != before:
                    changed.append(name)
                path.write_bytes(original)
    finally:
        runs.close()
    total = counts["ok"] + counts["error"] + len(crashes)
    print(f"\nfuzz: {total} cases in process: {counts['ok']} ran, {counts['error']} refused with an InputError, "
          f"{len(crashes)} crashed; {len(changed)} changed an input file")
    assert not crashes, f"{len(crashes)} of {total} cases crashed; the first:\n" + crashes[0]
    assert not changed, changed[:10]

    # The real command line on a sample: the same outcome, and the promised message and exit code.
    sample = cases[:: max(1, len(cases) // CLI_SAMPLE)][:CLI_SAMPLE]
    for path, description, content, result in sample:
        original = path.read_bytes()
        path.write_bytes(content.encode() if isinstance(content, str) else content)
        before = _digests(demo)
        out = tmp_path / "results.csv"
        out.unlink(missing_ok=True)
        try:
            run = _workbench("estimate", demo, "--particles", 6, "--iterations", 1, "--workers", 1, "--out", out)
        finally:
            assert _digests(demo) == before, f"{path.name}: {description} changed an input file"
            path.write_bytes(original)
        assert "Traceback" not in run.stderr, f"{path.name}: {description}\n{run.stderr}"
        if result == "ok":
            assert run.returncode == 0 and out.is_file(), f"{path.name}: {description}\n{run.stderr}"
        else:
            assert run.returncode == 2 and "workbench: error: " in run.stderr, \
                f"{path.name}: {description}\n{run.stderr}"
            assert not out.exists()
    print(f"fuzz: {len(sample)} of the dataset cases also ran as `workbench estimate` subprocesses")
