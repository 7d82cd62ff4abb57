"""Bad input, each measured failure as a test: nothing a user made is overwritten, and every bad input ends in
`workbench: error: FILE: problem` with exit code 2 before any work starts, never a traceback."""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import socket
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from inbox import Inbox

from workbench.app.engine.engine import DEMO_DIR
from workbench.errors import InputError
from workbench.evaluation import pool
from workbench.io.results import read_results_csv
from workbench.label import frame as labels
from workbench.sessions import store as sessions

pytestmark = pytest.mark.slow  # needs whole estimates: pybullet and OpenGL


def _workbench(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "workbench.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


def _refused(run, *words):
    """Exit code 2 with the promised message naming ``words``, no traceback, and no estimation started."""
    assert run.returncode == 2, run.stderr
    assert "workbench: error: " in run.stderr and "Traceback" not in run.stderr, run.stderr
    assert "frame 0:" not in run.stderr, "an estimate ran before the error"
    for w in words:
        assert w in run.stderr, (w, run.stderr)


def _digests(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def demo(tmp_path) -> Path:
    out = tmp_path / "demo"
    shutil.copytree(DEMO_DIR, out)
    return out


@pytest.fixture(scope="module")
def two_frames(tmp_path_factory) -> Path:
    """Two small generated scenes, for incremental results."""
    from workbench.synth import make_scenes

    out = tmp_path_factory.mktemp("two") / "data"
    make_scenes(out, ["touching"], 2, seed=3, width=320, height=240, sensor="kinect-like")
    return out


FAST = ("--particles", 6, "--iterations", 1, "--workers", 1)


# ----------------------------------------------------------------------------------------------------------------
# 1. estimate --out


def test_out_never_replaces_a_datasets_file_or_writes_inside_it(demo, tmp_path):
    before = _digests(demo)
    gt = demo / "test" / "000000" / "scene_gt.json"
    _refused(_workbench("estimate", demo, *FAST, "--out", gt), "scene_gt.json", "dataset folder")
    _refused(_workbench("estimate", demo, *FAST, "--out", gt, "--force"), "dataset folder")  # not even forced
    _refused(_workbench("estimate", demo, *FAST, "--out", demo / "models" / "r.csv"), "dataset folder")
    _refused(_workbench("estimate", demo, *FAST, "--out", demo / "test" / "000000" / "depth" / "r.csv"))
    assert _digests(demo) == before


def test_out_keeps_a_users_file_unless_forced_and_keeps_its_mode(demo, tmp_path):
    mine = tmp_path / "notes.txt"
    mine.write_text("my notes\n")
    mine.chmod(0o600)
    _refused(_workbench("estimate", demo, *FAST, "--out", mine), "notes.txt", "--force")
    assert mine.read_text() == "my notes\n" and stat.S_IMODE(mine.stat().st_mode) == 0o600

    run = _workbench("estimate", demo, *FAST, "--out", mine, "--force")
    assert run.returncode == 0, run.stderr
    assert len({r.obj_id for r in read_results_csv(mine)}) == 2 and stat.S_IMODE(mine.stat().st_mode) == 0o600

    # Our own results CSV may be replaced without --force (a rerun).
    run = _workbench("estimate", demo, *FAST, "--seed", 1, "--out", mine)
    assert run.returncode == 0, run.stderr
    assert stat.S_IMODE(mine.stat().st_mode) == 0o600


def test_out_is_checked_before_any_work(demo, tmp_path):
    (tmp_path / "a_file").write_text("x")
    _refused(_workbench("estimate", demo, "--out", tmp_path), "is a folder")
    _refused(_workbench("estimate", demo, "--out", tmp_path / "a_file" / "r.csv"), "is a file, not a folder")
    _refused(_workbench("estimate", demo, "--out", tmp_path / "r.csv", "--resume", "--force"), "--resume")
    assert not (tmp_path / "r.csv").exists()


# ----------------------------------------------------------------------------------------------------------------
# Incremental results and --resume


def test_results_are_written_frame_by_frame_and_resume_skips_written_frames(two_frames, tmp_path):
    from workbench.inference.config import EstimatorConfig
    from workbench.io.results import ResultsFile
    from workbench.problem.problem import ProblemConfig
    from workbench.run.runner import estimate_frames

    # A run that fails at its second frame keeps the first frame's results.
    broken = tmp_path / "broken"
    shutil.copytree(two_frames, broken)
    (broken / "test" / "000001" / "depth" / "000000.png").write_bytes(b"not a png")
    out = tmp_path / "r.csv"
    results = ResultsFile(out)
    with pytest.raises(InputError, match="000001"):
        estimate_frames(broken, [(0, 0), (1, 0)], EstimatorConfig(particles=6, iterations=1), ProblemConfig(), 1,
                        on_frame=results.add)
    first = read_results_csv(out)
    assert {(r.scene_id, r.im_id) for r in first} == {(0, 0)} and len({r.obj_id for r in first}) == 2

    # --resume estimates only the missing frame and keeps the written rows as they were.
    lines = out.read_text().splitlines()
    run = _workbench("estimate", two_frames, *FAST, "--out", out, "--resume")
    assert run.returncode == 0, run.stderr
    assert "1 of 2 frame(s) already" in run.stderr
    after = out.read_text().splitlines()
    assert after[: len(lines)] == lines
    assert {(r.scene_id, r.im_id) for r in read_results_csv(out)} == {(0, 0), (1, 0)}


def test_a_frame_estimated_into_a_log_file_says_how_far_it_is(demo, monkeypatch, capsys):
    from workbench.inference.config import EstimatorConfig
    from workbench.problem.problem import ProblemConfig
    from workbench.run import runner

    monkeypatch.setattr(runner, "LOG_EVERY_S", 0.0)  # every step, not every 10 s
    runner.estimate_frames(demo, [(0, 0)], EstimatorConfig(particles=6, iterations=2), ProblemConfig(), 1)
    err = capsys.readouterr().err  # captured: not a terminal, so no progress bar
    assert "scene 0 frame 0: step 1 of at most 3 after" in err
    assert "\r" not in err


def test_resume_refuses_a_file_that_is_not_ours(demo, tmp_path):
    mine = tmp_path / "mine.csv"
    mine.write_text("a,b\n1,2\n")
    _refused(_workbench("estimate", demo, "--out", mine, "--resume"), "nothing to resume")
    assert mine.read_text() == "a,b\n1,2\n"


# ----------------------------------------------------------------------------------------------------------------
# 2. make-scenes


def test_make_scenes_refuses_a_folder_that_is_not_empty(demo, tmp_path):
    from workbench.synth import make_scenes

    before = _digests(demo)
    _refused(_workbench("make-scenes", demo, "--categories", "touching", "--per-category", 1), "not empty", "--force")
    _refused(_workbench("make-scenes", demo, "--demo"), "not empty")
    assert _digests(demo) == before
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "keep.txt").write_text("x")
    # asked for: writes beside it
    make_scenes(mine, ["touching"], 1, seed=0, width=160, height=120, force=True, sensor="kinect-like")
    assert (mine / "keep.txt").read_text() == "x" and (mine / "scenes.json").is_file()


# ----------------------------------------------------------------------------------------------------------------
# 3 and 4. Parameters, checked before anything is loaded or started


@pytest.mark.parametrize("workers", [0, -3, 1000])
def test_workers_outside_the_machines_bound_are_refused(demo, tmp_path, workers):
    _refused(_workbench("estimate", demo, "--workers", workers, "--out", tmp_path / "r.csv"), "--workers",
             f"to {pool.max_workers()}")
    assert not (tmp_path / "r.csv").exists()


def test_worker_bound_follows_cores_and_memory():
    bound = pool.max_workers()
    assert 1 <= bound <= pool.usable_cores()
    memory = pool.available_memory()
    if memory is not None:
        assert bound <= max(1, memory // pool.WORKER_MEMORY_BYTES)
    assert pool.check_workers(1) == 1
    with pytest.raises(InputError):
        pool.check_workers(True)  # a boolean is not a count


def test_bad_seed_and_other_parameters_are_refused_before_work(demo, tmp_path):
    _refused(_workbench("estimate", demo, "--seed", -1, "--out", tmp_path / "r.csv"), "--seed")
    _refused(_workbench("estimate", demo, "--max-render-pixels", 10, "--out", tmp_path / "r.csv"), "render")
    _refused(_workbench("estimate", demo, "--sigma-pos", 50, "--out", tmp_path / "r.csv"), "sigma")
    _refused(_workbench("make-scenes", tmp_path / "new", "--seed", -2), "--seed")
    _refused(_workbench("bench", "--speed", "--workers", 0), "--workers")
    _refused(_workbench("serve", "--demo", "--port", 70000), "--port")
    assert not (tmp_path / "new").exists() and not (tmp_path / "r.csv").exists()


def _saved_session(demo: Path, folder: Path) -> Path:
    from workbench.evaluation import LocalEvaluator
    from workbench.inference.config import EstimatorConfig
    from workbench.inference.estimator import Estimator
    from workbench.problem.build import load_bop_problem

    frame, problem = load_bop_problem(demo, 0, 0)
    ev = LocalEvaluator(problem)
    try:
        est = Estimator(problem, EstimatorConfig(particles=6, iterations=5), ev)
        est.step()
        state = sessions.session_state_from(est, sessions.frame_ref_for(demo, frame, problem), None)
        return sessions.save_session(folder, "s", state)
    finally:
        ev.close()


def _edit(path: Path, change) -> None:
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize("change, words", [
    (lambda d: d["estimator_config"].__setitem__("seed", -1), "seed"),
    (lambda d: d["problem_config"]["physics"].__setitem__("max_steps", 10**12), "max_steps"),
    (lambda d: d["estimator"].__setitem__("beta", -3.0), "beta"),
    (lambda d: d["support"]["T_cam_world"][0].__setitem__(0, -d["support"]["T_cam_world"][0][0]), "rotation"),
    (lambda d: d["labels"].__setitem__(0, np.diag([1.0, 1.0, -1.0, 1.0]).tolist()), "determinant -1"),
    (lambda d: d["labels"].__setitem__(0, [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]), "bottom row"),
])
def test_session_values_get_the_command_lines_checks(demo, tmp_path, change, words):
    path = _saved_session(demo, tmp_path / "sessions")
    _edit(path, change)
    with pytest.raises(InputError, match=words) as err:
        sessions.load_session(path)
    assert err.value.path == str(path)


def test_session_with_a_bad_seed_is_refused_by_serve(demo, tmp_path):
    path = _saved_session(demo, tmp_path / "sessions")
    _edit(path, lambda d: d["estimator_config"].__setitem__("seed", -1))
    _refused(_workbench("serve", "--session", path), "s.json", "seed")


# ----------------------------------------------------------------------------------------------------------------
# 5. Values of the wrong type


@pytest.mark.parametrize("file, change, words", [
    ("test/000000/scene_camera.json", lambda d: d["0"].__setitem__("depth_scale", "abc"), "depth_scale"),
    ("test/000000/scene_gt.json", lambda d: d["0"][0].__setitem__("obj_id", "six"), "obj_id"),
    ("camera.json", lambda d: d.__setitem__("width", "wide"), "width"),
    ("test/000000/scene_camera.json", lambda d: d.__setitem__("0", [d["0"]]), "image 0"),
    ("models/models_info.json", lambda d: d["5"].__setitem__("symmetries_discrete", 7), "symmetries_discrete"),
])
def test_wrong_types_name_file_and_key(demo, tmp_path, file, change, words):
    _edit(demo / file, change)
    _refused(_workbench("estimate", demo, *FAST, "--out", tmp_path / "r.csv"), Path(file).name, words)


def test_scene_camera_as_a_list_is_refused(demo, tmp_path):
    cam = demo / "test" / "000000" / "scene_camera.json"
    cam.write_text(json.dumps([json.loads(cam.read_text())["0"]]))
    _refused(_workbench("estimate", demo, *FAST, "--out", tmp_path / "r.csv"), "scene_camera.json", "object")


def test_plain_frame_types_and_complex_depth(tmp_path):
    from workbench.io.plainframe import load_plain_frame

    depth = np.full((48, 64), 0.8)
    np.save(tmp_path / "d.npy", depth)
    mesh = tmp_path / "box.obj"
    import trimesh

    trimesh.creation.box((0.05, 0.05, 0.05)).export(mesh)
    intr = {"fx": 60.0, "fy": 60.0, "cx": 32.0, "cy": 24.0, "width": 64, "height": 48}
    for key, value in [("width", "wide"), ("fx", "sixty"), ("depth_scale", "abc"), ("height", 48.5)]:
        (tmp_path / "k.json").write_text(json.dumps({**intr, key: value}))
        with pytest.raises(InputError, match=key) as err:
            load_plain_frame(tmp_path / "d.npy", tmp_path / "k.json", [mesh])
        assert err.value.path == str(tmp_path / "k.json")
    (tmp_path / "k.json").write_text(json.dumps(intr))
    np.save(tmp_path / "c.npy", depth.astype(np.complex128))
    with pytest.raises(InputError, match="real numbers"):
        load_plain_frame(tmp_path / "c.npy", tmp_path / "k.json", [mesh])


# ----------------------------------------------------------------------------------------------------------------
# 6. serve


def test_serve_fails_on_a_busy_port_naming_it(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        _refused(_workbench("serve", "--demo", "--port", port, timeout=120), f"port {port}", "in use")


def test_serve_fails_on_a_missing_dataset_or_frame(demo, tmp_path):
    _refused(_workbench("serve", tmp_path / "nowhere", timeout=120), "nowhere", "not found")
    _refused(_workbench("serve", demo, "--scene", 0, "--frame", 9, timeout=120), "no frame 9")


def test_serve_prints_load_errors_to_the_terminal(demo, caplog):
    from workbench.app.ui.server import serve
    from workbench.inference.config import EstimatorConfig

    (demo / "test" / "000000" / "depth" / "000000.png").write_bytes(b"broken")
    caplog.set_level(logging.WARNING)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    handle = serve(dataset=demo, block=False, port=port, workers=1, config=EstimatorConfig(particles=8))
    try:
        assert handle.app.wait_for(lambda s: s.failures, 120)
    finally:
        handle.stop()
    assert any(r.levelno == logging.WARNING and "000000.png" in r.getMessage() for r in caplog.records)


def test_demo_labels_are_saved_into_a_copy_never_into_the_package(workbench_home):
    from workbench.app import protocol as p
    from workbench.app.engine.engine import Engine
    from workbench.inference.config import EstimatorConfig

    before = _digests(DEMO_DIR)
    inbox = Inbox()
    engine = Engine(inbox, workers=1)
    try:
        engine.handle(p.Load(p.Source(demo=True), EstimatorConfig(particles=6), "robust"))
        engine.step()
        engine.handle(p.SetLabels((engine.estimator.estimate[0].copy(), None)))
        engine.handle(p.SaveLabels(overwrite_original=False))
    finally:
        engine.close()
    saved = [m for m in inbox if isinstance(m, p.Saved)]
    assert saved, [m for m in inbox if isinstance(m, p.Failure)]
    assert Path(saved[0].path).resolve().is_relative_to(Path(workbench_home).resolve())
    assert _digests(DEMO_DIR) == before


# ----------------------------------------------------------------------------------------------------------------
# 7. Hypotheses and labels that are not rigid poses


def test_reflections_and_bad_bottom_rows_are_refused_at_the_edge(demo, tmp_path):
    from workbench.evaluation import LocalEvaluator
    from workbench.problem.build import load_bop_problem

    frame, problem = load_bop_problem(demo, 0, 0)
    good = np.stack([np.eye(4), np.eye(4)])
    good[:, 2, 3] = 0.05
    reflected = good.copy()
    reflected[0, :3, :3] = np.diag([1.0, 1.0, -1.0])
    bottom = good.copy()
    bottom[1, 3] = [0.0, 0.0, 0.5, 1.0]
    ev = LocalEvaluator(problem)
    try:
        assert np.isfinite(ev.evaluate(good[None]).projected).all()
        for bad, words in ((reflected, "determinant -1"), (bottom, "bottom row")):
            with pytest.raises(InputError, match=words):
                ev.evaluate(bad[None])
            with pytest.raises(InputError, match=words):
                labels.snap_to_plausible(problem, bad, ev)
            with pytest.raises(InputError, match=words):
                labels.save_labels(demo, 0, 0, problem.camera.T_cam_world, list(bad), [6, 5])
    finally:
        ev.close()
    assert not (demo / "test" / "000000" / labels.LABELS_FILE).exists()
