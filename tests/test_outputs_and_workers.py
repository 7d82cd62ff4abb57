"""Nothing lost, nothing stuck, the parts that need no physics, rendering, Ray or a browser: damaged
caches rebuilt, results files locked and guarded, every output a command writes checked, a dead evaluation worker
restarted with its batch retried."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh

from workbench.meshes import cache

# ----------------------------------------------------------------------------------------------------------------
# Caches: verified on read, rebuilt with a warning naming the file

DAMAGE = {
    "emptied": lambda p: p.write_bytes(b""),
    "truncated": lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]),
    "garbage": lambda p: p.write_bytes(b"not a zip file at all" * 10),
    "one byte flipped": lambda p: p.write_bytes(_flip(p.read_bytes())),
    "no checksum": lambda p: np.savez(open(p, "wb"), vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 2]])),
    "folder": lambda p: (p.unlink(), p.mkdir()),
}


def _flip(data: bytes) -> bytes:
    # a byte inside the stored arrays (uncompressed npz: the data lies after the member headers)
    i = len(data) // 3
    return data[:i] + bytes([data[i] ^ 0xFF]) + data[i + 1:]


def _collision_shape():
    from workbench.physics.collision import BOX, CollisionShape

    return CollisionShape(BOX, np.eye(4), np.array([0.05, 0.03, 0.02]), (), 0.9, 0.004)


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_collision_cache_file_is_named_and_rebuilt(damage, tmp_path, caplog):
    from workbench.physics import collision

    builds = []

    def compute():
        builds.append(1)
        return _collision_shape()

    collision._cached("k" * 40, tmp_path, compute)
    path = tmp_path / ("k" * 40 + ".npz")
    assert path.is_file() and builds == [1]
    collision._MEMORY_CACHE.clear()
    DAMAGE[damage](path)
    with caplog.at_level(logging.WARNING):
        shape = collision._cached("k" * 40, tmp_path, compute)
    assert builds == [1, 1] and shape.kind == "box"
    assert str(path) in caplog.text and "rebuilding" in caplog.text
    collision._MEMORY_CACHE.clear()
    caplog.clear()
    collision._cached("k" * 40, tmp_path, compute)  # rebuilt for good: read back without a warning
    assert builds == [1, 1] and not caplog.text
    collision._MEMORY_CACHE.clear()


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_render_cache_file_is_named_and_rebuilt(damage, tmp_path, caplog, monkeypatch):
    from workbench.render import depth

    builds = []

    def decimate(mesh, max_error):
        builds.append(1)
        return trimesh.creation.icosphere(1)

    monkeypatch.setattr(depth, "_decimate_within", decimate)
    mesh = trimesh.creation.icosphere(4)
    depth.render_mesh(mesh, cache_dir=tmp_path)
    (path,) = tmp_path.glob("*.npz")
    depth._MESH_CACHE.clear()
    DAMAGE[damage](path)
    with caplog.at_level(logging.WARNING):
        simple = depth.render_mesh(mesh, cache_dir=tmp_path)
    assert builds == [1, 1] and len(simple.faces) == 80
    assert str(path) in caplog.text and "rebuilding" in caplog.text
    depth._MESH_CACHE.clear()


def test_a_cache_that_cannot_be_written_is_a_warning_not_an_error(tmp_path, caplog):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with caplog.at_level(logging.WARNING):
        cache.save(blocker / "below" / "a.npz", {"a": np.zeros(3)})
    assert "could not write the cache file" in caplog.text


# ----------------------------------------------------------------------------------------------------------------
# Results files: one run at a time, never a dataset's file, never another dataset's results, written whole

import errno  # noqa: E402
import hashlib  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

from workbench.cli import DEMO_DATASET, main  # noqa: E402

ROW = "0,0,5,1,1 0 0 0 1 0 0 0 1,0 0 500,1.0"


@pytest.fixture
def demo(tmp_path) -> Path:
    out = tmp_path / "demo"
    shutil.copytree(DEMO_DATASET, out)
    return out


def _digests(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _refused(capsys, argv, *words) -> str:
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("workbench: error: ") and "Traceback" not in err, err
    for w in words:
        assert w in err, err
    return err


def _results(path: Path, *rows: str) -> Path:
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + "".join(r + "\n" for r in rows))
    return path


def test_a_second_run_on_the_same_out_is_refused_naming_the_first_runs_pid(demo, tmp_path, capsys):
    out = _results(tmp_path / "same.csv", ROW)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from workbench.io.outputs import OutputLock; "
                               f"OutputLock({str(out)!r}).acquire(); print('locked', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = out.read_bytes()
        _refused(capsys, ["estimate", demo, "--out", out, "--resume"], str(out), f"pid {holder.pid}",
                 "another run")
        _refused(capsys, ["estimate", demo, "--out", out, "--force"], f"pid {holder.pid}")
        assert out.read_bytes() == before
    finally:
        holder.kill()
        holder.wait()
    # The lock dies with its process: the file can be written again.
    from workbench.io.results import ResultsFile

    results = ResultsFile.open(out, resume=True)
    results.close()


def test_a_lock_is_released_and_taken_again_in_one_process(tmp_path):
    from workbench.errors import InputError
    from workbench.io.outputs import OutputLock

    out = tmp_path / "r.csv"
    with OutputLock(out):
        with pytest.raises(InputError, match=f"pid {os.getpid()}"):
            OutputLock(out).acquire()
    with OutputLock(out):
        pass
    assert not (tmp_path / ".r.csv.lock").exists()


# A process that may write no byte (RLIMIT_FSIZE 0, SIGXFSZ ignored): the kernel's EFBIG, as a full disk's ENOSPC.
NO_BYTES = ("import resource, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
            "resource.setrlimit(resource.RLIMIT_FSIZE, (0, 0)); from workbench.cli import main; sys.exit(main())")


def test_a_lock_that_cannot_be_written_is_an_error_and_leaves_no_lock_file(demo, tmp_path):
    out = tmp_path / "r.csv"
    root = Path(__file__).resolve().parent.parent
    done = subprocess.run([sys.executable, "-c", NO_BYTES, "estimate", str(demo), "--out", str(out)],
                          capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(root)})
    assert done.returncode == 2 and done.stderr.startswith("workbench: error: ") and "Traceback" not in done.stderr
    assert f"{out}: cannot write the lock file" in done.stderr, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo"]


@pytest.mark.parametrize("command", ["estimate", "track"])
def test_posterior_and_out_on_one_file_are_refused_before_any_work(demo, tmp_path, capsys, command):
    """The posterior JSON written over the results CSV lost every result, with exit 0."""
    out = _results(tmp_path / "same.csv", ROW)
    before = out.read_bytes()
    scene = ["--scene", "0"] if command == "track" else []
    _refused(capsys, [command, demo, *scene, "--out", out, "--posterior", tmp_path / "." / "same.csv", "--force"],
             "--posterior", "--out", "different files")
    assert out.read_bytes() == before


def test_a_second_run_on_the_same_posterior_is_refused_naming_the_first_runs_pid(demo, tmp_path, capsys):
    """Two runs with different --out but one --posterior: the second is refused, not left to replace the first's
    frames."""
    from workbench.io.outputs import OutputLock

    posterior = tmp_path / "posterior.json"
    with OutputLock(posterior, flag="--posterior"):
        _refused(capsys, ["estimate", demo, "--out", tmp_path / "b.csv", "--posterior", posterior],
                 str(posterior), f"pid {os.getpid()}", "another --posterior")
    assert not posterior.exists() and not (tmp_path / "b.csv").exists()


def test_score_refuses_its_json_or_diagram_on_the_results_or_on_each_other(demo, tmp_path, capsys):
    results = _results(tmp_path / "r.csv", ROW)
    before = results.read_bytes()
    _refused(capsys, ["score", demo, results, "--json", results, "--force"], "--json", "different files")
    _refused(capsys, ["score", demo, results, "--json", tmp_path / "x", "--reliability", tmp_path / "x"],
             "--reliability", "--json")
    assert results.read_bytes() == before and not (tmp_path / "x").exists()


def test_out_never_replaces_a_file_of_the_datasets_root_even_with_force(demo, capsys):
    before = _digests(demo)
    for name in ("camera.json", "scenes.json"):
        _refused(capsys, ["estimate", demo, "--out", demo / name, "--force"], str(demo / name), "never replaced")
    assert _digests(demo) == before


def test_resume_refuses_the_results_of_another_dataset(demo, tmp_path, capsys):
    out = _results(tmp_path / "other.csv", ROW, "7,3,5,1,1 0 0 0 1 0 0 0 1,0 0 500,1.0")
    before = out.read_bytes()
    _refused(capsys, ["estimate", demo, "--out", out, "--resume"], "line 3", "scene 7 image 3", "another dataset")
    out = _results(tmp_path / "objects.csv", "0,0,42,1,1 0 0 0 1 0 0 0 1,0 0 500,1.0")
    _refused(capsys, ["estimate", demo, "--out", out, "--resume"], "line 2", "object 42")
    assert (tmp_path / "other.csv").read_bytes() == before


def test_resume_names_a_cut_line_and_a_bom(demo, tmp_path, capsys):
    out = _results(tmp_path / "cut.csv", ROW)
    out.write_text(out.read_text() + "0,1,5,1,1 0 0")
    _refused(capsys, ["estimate", demo, "--out", out, "--resume"], "line 3", "cannot be resumed")
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + _results(tmp_path / "plain.csv", ROW).read_bytes())
    _refused(capsys, ["estimate", demo, "--out", bom, "--resume"], "byte order mark")


def test_no_frames_in_a_split_is_said_without_none(demo, capsys):
    err = _refused(capsys, ["estimate", demo, "--split", "models", "--out", demo.parent / "r.csv"])
    assert "None" not in err


def test_a_full_disk_keeps_the_old_results_and_says_so(tmp_path, monkeypatch):
    from workbench.errors import InputError
    from workbench.io.results import ResultRow, ResultsFile

    out = _results(tmp_path / "r.csv", ROW)
    before = out.read_bytes()

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    results = ResultsFile(out, [ROW])
    with pytest.raises(InputError, match="No space left on device.*kept"):
        results.add([ResultRow(0, 1, 5, 1.0, np.eye(4), 1.0)])
    assert out.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["r.csv"]


def test_results_through_a_symlink_keep_the_link(tmp_path):
    from workbench.io.results import ResultRow, ResultsFile

    target = _results(tmp_path / "real.csv", ROW)
    link = tmp_path / "link.csv"
    link.symlink_to(target)
    results = ResultsFile.open(link, resume=True)
    try:
        results.add([ResultRow(0, 1, 5, 1.0, np.eye(4), 1.0)])
    finally:
        results.close()
    assert link.is_symlink() and len(target.read_text().splitlines()) == 3


# ----------------------------------------------------------------------------------------------------------------
# Every other file a command writes: score --json, bench --out, sessions


def test_score_json_gets_the_guards_of_every_output(demo, tmp_path, capsys):
    results = _results(tmp_path / "results.csv", ROW)
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes\n")
    before, dataset = results.read_bytes(), _digests(demo)
    _refused(capsys, ["score", demo, results, "--json", results], "results CSV being scored")
    _refused(capsys, ["score", demo, results, "--json", notes], "notes.txt", "--force")
    gt = demo / "test" / "000000" / "scene_gt.json"
    _refused(capsys, ["score", demo, results, "--json", gt, "--force"], "dataset folder")
    _refused(capsys, ["score", demo, results, "--json", demo / "camera.json", "--force"], "never replaced")
    _refused(capsys, ["score", demo, results, "--json", tmp_path], "is a folder")
    _refused(capsys, ["score", demo, results, "--json", "/dev/full"], "not a regular file")
    assert results.read_bytes() == before and notes.read_text() == "my notes\n" and _digests(demo) == dataset
    scores = tmp_path / "scores.json"
    assert main(["score", str(demo), str(results), "--json", str(scores)]) == 0
    assert main(["score", str(demo), str(results), "--json", str(scores)]) == 0  # ours: replaced
    assert main(["score", str(demo), str(results), "--json", str(notes), "--force"]) == 0
    capsys.readouterr()


def test_score_json_on_a_full_disk_is_an_error_naming_it(demo, tmp_path, capsys, monkeypatch):
    results = _results(tmp_path / "results.csv", ROW)

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    _refused(capsys, ["score", demo, results, "--json", tmp_path / "s.json"], "s.json", "No space left")
    assert not (tmp_path / "s.json").exists()


def test_bench_out_replaces_only_what_bench_wrote(demo, tmp_path, capsys):
    out = tmp_path / "bench-out"
    out.mkdir()
    (out / "report.md").write_text("my report\n")
    _refused(capsys, ["bench", demo, "--out", out], "report.md", "move the file away")
    (out / "report.md").unlink()
    (out / "results_pipf.csv").write_text("mine\n")
    _refused(capsys, ["bench", demo, "--out", out, "--methods", "pipf"], "results_pipf.csv")
    assert (out / "results_pipf.csv").read_text() == "mine\n"
    _refused(capsys, ["bench", demo, "--out", demo / "scenes.json"], "is a file")


def test_sessions_are_saved_only_where_a_session_may_be(demo, tmp_path):
    from workbench.errors import InputError
    from workbench.sessions.store import check_sessions_dir, save_session

    (tmp_path / "a_file").write_text("x")
    for bad, words in [(tmp_path / "a_file", "is a file"), (tmp_path / "a_file" / "below", "is a file"),
                       (demo / "test" / "000000" / "sessions", "dataset folder"),
                       (demo / "models" / "s", "dataset folder")]:
        with pytest.raises(InputError, match=words):
            check_sessions_dir(bad)
        with pytest.raises(InputError, match=words):
            save_session(bad, "run", None)
    (tmp_path / "mine.json").write_text('{"my": "notes"}')
    with pytest.raises(InputError, match="not a session file"):
        save_session(tmp_path, "mine", None, overwrite=True)
    assert (tmp_path / "mine.json").read_text() == '{"my": "notes"}'


def test_serve_refuses_a_session_whose_dataset_is_gone(demo, tmp_path, capsys, monkeypatch):
    from types import SimpleNamespace

    from workbench.app.ui import server
    from workbench.sessions import store as sessions

    state = SimpleNamespace(frame=SimpleNamespace(dataset=str(tmp_path / "gone"), files={"x.json": "0"}))
    monkeypatch.setattr(sessions, "load_session", lambda path: state)
    served = []
    monkeypatch.setattr(server, "serve", lambda **kw: served.append(kw))
    session = tmp_path / "s.json"
    session.write_text("{}")
    _refused(capsys, ["serve", "--session", session], str(session), "dataset folder not found")
    state.frame.dataset = str(demo)
    _refused(capsys, ["serve", "--session", session], "x.json: missing")
    _refused(capsys, ["serve", "--demo", "--sessions-dir", demo / "models"], "dataset folder")
    assert not served


# ----------------------------------------------------------------------------------------------------------------
# A dead evaluation worker: started again, its part retried, one WARNING, the same results


def toy_worker(problem):
    """A worker's evaluator for the pool tests (module level: spawned workers import it by name): the toy
    evaluator, which dies (exit code 9) in the middle of its first batch while $DIE_ONCE names a file that is not
    there yet, once per such file."""
    sys.path.insert(0, str(Path(__file__).parent))
    from toy import ToyEvaluator, toy_target

    evaluator = ToyEvaluator(problem, toy_target(problem))
    marker = os.environ.get("DIE_ONCE")
    evaluate = evaluator.evaluate

    def dying(*args, **kwargs):
        if marker and not os.path.exists(marker):
            open(marker, "w").close()
            os._exit(9)
        return evaluate(*args, **kwargs)

    evaluator.evaluate = dying
    return evaluator


@pytest.fixture
def toy_batch():
    """The toy problem (tests/toy.py) and 12 hypotheses of it."""
    sys.path.insert(0, str(Path(__file__).parent))
    from toy import toy_problem

    problem = toy_problem()
    rng = np.random.default_rng(0)
    hypotheses = np.tile(np.eye(4), (12, len(problem.models), 1, 1))
    hypotheses[..., :2, 3] = rng.uniform(-0.1, 0.1, (12, len(problem.models), 2))
    hypotheses[..., 2, 3] = 0.1
    return problem, hypotheses


def test_a_dead_pool_worker_is_restarted_and_its_batch_retried_with_the_same_results(toy_batch, tmp_path,
                                                                                      monkeypatch, caplog):
    from workbench.evaluation import PoolEvaluator

    problem, hypotheses = toy_batch
    expected = toy_worker(problem).evaluate(hypotheses)
    monkeypatch.setenv("DIE_ONCE", str(tmp_path / "died"))
    pool = PoolEvaluator(problem, 2, max_retries=1, factory=toy_worker)
    try:
        with caplog.at_level(logging.WARNING):
            got = pool.evaluate(hypotheses)
            again = pool.evaluate(hypotheses)  # the restarted worker stays
    finally:
        pool.close()
    for result in (got, again):
        np.testing.assert_array_equal(result.projected, expected.projected)
        np.testing.assert_array_equal(result.loglik, expected.loglik)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "died (exit code 9)" in warnings[0].getMessage()
    assert "retry 1 of 1" in warnings[0].getMessage()


def test_a_worker_that_keeps_dying_ends_after_max_retries(toy_batch):
    from workbench.evaluation import PoolEvaluator, WorkerCrashed

    problem, hypotheses = toy_batch
    pool = PoolEvaluator(problem, 1, max_retries=0, factory=toy_worker)
    try:
        pool._procs[0].kill()
        pool._procs[0].join()
        with pytest.raises(WorkerCrashed, match="died"):
            pool.evaluate(hypotheses)
    finally:
        pool.close()


def test_a_script_without_a_main_guard_is_told_so_instead_of_hanging(tmp_path):
    """Each spawned worker imports the script again; unguarded, its own pool start fails there and the worker dies
    before reading the problem. The problem (meshes: larger than a pipe's buffer) used to go as the process's
    arguments, whose write ``multiprocessing`` never lets fail: the script hung for ever."""
    script = tmp_path / "unguarded.py"
    script.write_text("from workbench.cli import DEMO_DATASET\nfrom workbench.evaluation import make_evaluator\n"
                      "from workbench.problem.build import load_bop_problem\n"
                      "_, problem = load_bop_problem(DEMO_DATASET, 0, 0)\nmake_evaluator(problem, 2)\n")
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert run.returncode != 0
    assert "WorkerCrashed: evaluation worker 1 exited as it started" in run.stderr
    assert 'if __name__ == "__main__":' in run.stderr


def test_workers_leave_quietly_when_the_main_process_is_gone(capfd):
    from workbench.evaluation import pool

    class Gone:
        def __init__(self):
            self.messages = iter(["the problem", ("evaluate", np.zeros((0, 1, 4, 4)))])

        def recv(self):
            return next(self.messages)

        def send(self, value):
            raise BrokenPipeError(32, "Broken pipe")

        def close(self):
            pass

    class Quiet:
        def __init__(self, problem):
            pass

        def evaluate(self, *args):
            return None

        def close(self):
            pass

    pool._worker(Gone(), Quiet)  # returns, no traceback
    assert "Traceback" not in capfd.readouterr().err


def test_sigterm_ends_a_command_with_a_message_and_no_traceback(tmp_path):
    script = ("import time, workbench.cli as c\n"
              "def slow(args):\n    print('started', flush=True)\n    time.sleep(60)\n"
              "c._cmd_score = slow\nraise SystemExit(c.main(['score', '.', 'r.csv']))\n")
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=tmp_path)
    assert proc.stdout.readline().strip() == "started"
    proc.terminate()
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 143 and "stopped by SIGTERM" in err and "Traceback" not in err, err


# ----------------------------------------------------------------------------------------------------------------
# Clear words for what went wrong


@pytest.mark.parametrize("address, words", [("http://127.0.0.1:8265", "dashboard"), ("http://[::1", "web address"),
                                            ("[::1", "HOST:PORT"), ("host/path:1", "HOST:PORT")])
def test_a_ray_address_that_is_no_cluster_address_is_named(address, words, capsys):
    _refused(capsys, ["estimate", str(DEMO_DATASET), "--engine", "ray", "--ray-address", address,
                      "--out", "/nonexistent-dir-for-the-test/r.csv"], "--ray-address", words)


def test_a_depth_image_of_another_size_than_its_intrinsics_is_refused(demo, tmp_path, capsys):
    from PIL import Image

    png = demo / "test" / "000000" / "depth" / "000000.png"
    image = Image.open(png)
    image.resize((image.width * 2, image.height * 2), Image.NEAREST).save(png)
    (demo / "camera.json").unlink()  # as in ycbv-real-dev: no image size but the depth's own
    _refused(capsys, ["estimate", demo, "--out", tmp_path / "r.csv"], "scene_camera.json", "far from the centre",
             "another resolution")


def test_score_without_ground_truth_says_so_in_its_own_words(demo, tmp_path, capsys):
    (demo / "test" / "000000" / "scene_gt.json").unlink()
    err = _refused(capsys, ["score", demo, _results(tmp_path / "r.csv", ROW)], "no scene_gt.json",
                   "nothing to score")
    assert "object_ids" not in err


def test_a_mesh_far_too_large_is_not_called_metres(demo, tmp_path, capsys):
    ply = demo / "models" / "obj_000005.ply"
    mesh = trimesh.load(ply)
    mesh.apply_scale(1000)
    mesh.export(ply)
    err = _refused(capsys, ["score", demo, _results(tmp_path / "r.csv", ROW)], "obj_000005.ply", "micrometres")
    assert "in metres" not in err


# ----------------------------------------------------------------------------------------------------------------
# Heavy meshes: said, done once


def test_long_work_is_announced_and_never_silent_for_longer_than_the_interval(capfd):
    from workbench.meshes.heavy import announced

    def busy(seconds):  # holds the GIL, as open3d's decimation does
        import time

        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            sum(range(1000))

    with announced("simplifying obj_000006.ply (1.3M faces) for collision and rendering, once", first_s=0.3,
                   every_s=0.4):
        busy(1.6)
    lines = capfd.readouterr().err.splitlines()
    assert lines[0] == "workbench: simplifying obj_000006.ply (1.3M faces) for collision and rendering, once ..."
    assert 1 <= sum(line.startswith("workbench: still simplifying") for line in lines) <= 4
    assert lines[-1].startswith("workbench: done simplifying") and "cached" in lines[-1]
    with announced("a cache hit", first_s=1.0):
        pass
    assert capfd.readouterr().err == ""

def test_a_killed_runs_announcements_stop_with_it():
    """The speaker shares the run's stderr: while it lives the pipe stays open. Killed mid-announcement, the run
    leaves no speaker behind that goes on saying "still estimating" for ever."""
    import signal
    import threading

    script = ("import time\nfrom workbench.meshes.heavy import announced\n"
              "with announced('estimating scene 1 frame 1', first_s=0.0, every_s=0.2):\n    time.sleep(600)\n")
    run = subprocess.Popen([sys.executable, "-c", script], stderr=subprocess.PIPE, text=True)
    assert "estimating scene 1 frame 1 ..." in run.stderr.readline()
    run.send_signal(signal.SIGKILL)
    run.wait()
    done = {}
    reader = threading.Thread(target=lambda: done.setdefault("rest", run.stderr.read()), daemon=True)
    reader.start()
    reader.join(60)  # the speaker's pipe reaches its end once the speaker has stopped
    assert "rest" in done, "the killed run's speaker is still announcing"



def test_a_heavy_mesh_is_worked_on_as_a_lighter_one(monkeypatch):
    from workbench.meshes import heavy

    sphere = trimesh.creation.icosphere(5)  # 20480 faces
    monkeypatch.setattr(heavy, "HEAVY_FACES", 10_000)
    monkeypatch.setattr(heavy, "WORKING_FACES", 2_000)
    work = heavy.working_mesh(sphere)
    assert len(work.faces) <= 2_000 and heavy.working_mesh(sphere) is work
    assert np.abs(np.linalg.norm(work.vertices, axis=1) - 1).max() < 0.05
    light = trimesh.creation.icosphere(2)
    assert heavy.working_mesh(light) is light


def test_the_search_lays_a_heavy_mesh_on_a_reduced_hull_and_once_per_shape():
    from workbench.inference.search.moves import resting

    sphere = trimesh.creation.icosphere(6, radius=0.04)  # 40962 vertices, all on its hull
    hull = resting.reduced_hull(sphere)
    assert len(hull.vertices) <= resting.REDUCED_HULL_VERTICES < len(sphere.convex_hull.vertices)
    assert np.abs(np.linalg.norm(hull.vertices, axis=1) - 0.04).max() < 1e-9  # hull points of the sphere itself
    # Within 1.5 mm of the full hull: every face's plane passes that close to the sphere's centre-most extent.
    distance_to_centre = np.abs(np.einsum("fi,fi->f", hull.face_normals, hull.triangles[:, 0]))
    assert 0.04 - distance_to_centre.min() < 0.0015
    box = trimesh.creation.box(extents=[0.1, 0.06, 0.2])
    assert resting.reduced_hull(box).vertices.shape == box.convex_hull.vertices.shape  # light hulls as they are
    first = resting.resting_poses(box)
    again = resting.resting_poses(trimesh.creation.box(extents=[0.1, 0.06, 0.2]))  # the next frame's load
    assert again is first and not first.rotations.flags.writeable


def test_loading_a_heavy_mesh_says_so_and_a_light_one_says_nothing(tmp_path, capfd, monkeypatch):
    import time

    from workbench.io import bop
    from workbench.meshes import heavy

    trimesh.creation.icosphere(3, radius=40.0).export(tmp_path / "obj_000006.ply")  # 1280 faces, mm
    trimesh.creation.icosphere(1, radius=40.0).export(tmp_path / "obj_000005.ply")  # 80 faces
    trimesh.creation.icosphere(3, radius=40.0).export(tmp_path / "scan.obj")
    assert heavy.ply_faces(tmp_path / "obj_000006.ply") == 1280 and heavy.ply_faces(tmp_path / "scan.obj") is None
    monkeypatch.setattr(heavy, "HEAVY_FACES", 1000)
    monkeypatch.setattr(heavy, "FIRST_S", 0.1)
    read = bop._read_mesh

    def slow_read(path, scale):  # as a 1.3M-face PLY takes seconds to read and merge
        time.sleep(1.0)
        return read(path, scale)

    monkeypatch.setattr(bop, "_read_mesh", slow_read)
    mesh = bop.read_mesh(tmp_path / "obj_000006.ply", 0.001)
    assert len(mesh.faces) == 1280 and np.allclose(mesh.extents, 0.08, atol=1e-3)
    lines = capfd.readouterr().err.splitlines()
    assert lines[0] == "workbench: loading obj_000006.ply (1280 faces) ..."
    assert lines[-1].startswith("workbench: done loading obj_000006.ply (1280 faces) in ") and "cached" not in lines[-1]
    bop.read_mesh(tmp_path / "obj_000005.ply", 0.001)  # as slow, but light: not a word, no announcing process
    assert capfd.readouterr().err == ""
    monkeypatch.setattr(heavy, "HEAVY_FILE_BYTES", 1000)  # no face count in its header: its size decides
    bop.read_mesh(tmp_path / "scan.obj", 0.001)
    assert capfd.readouterr().err.splitlines()[0].startswith("workbench: loading scan.obj (0 MB) ...")
    with pytest.raises(bop.InputError):  # a failed load is not "done"
        with heavy.announced("loading nothing", first_s=0.0):
            time.sleep(0.2)
            raise bop.InputError("x", "corrupt")
    assert "done" not in capfd.readouterr().err


def test_the_particles_of_a_heavy_mesh_start_from_its_lowest_point_without_its_hull(monkeypatch):
    from workbench.geometry import random_rotations
    from workbench.inference.smc import particles
    from workbench.meshes import heavy
    from workbench.problem.scene import ObjectModel, Table

    rotations = random_rotations(np.random.default_rng(0), 50)
    box = trimesh.creation.box(extents=(0.1, 0.06, 0.2))
    box.vertices += (0.01, -0.02, 0.03)
    exact = np.min(np.einsum("nij,vj->nvi", rotations, box.convex_hull.vertices)[..., 2], axis=1)
    assert np.allclose(heavy.lowest_points(rotations, box.vertices), exact, atol=1e-12)
    ball = trimesh.creation.icosphere(6, radius=0.05)  # 40,962 vertices, all on its hull
    monkeypatch.setattr(heavy, "LOWEST_SAMPLE", 5000)
    sampled = heavy.lowest_points(rotations, ball.vertices)
    assert np.all(sampled >= -0.05) and np.all(sampled < -0.05 + 2e-4)  # 5,000 of them: within 0.2 mm
    table = Table(-0.5, 0.5, -0.4, 0.4)
    light = particles.initial_particles(np.random.default_rng(3), 40, [ObjectModel(6, ball)], table, "6dof")
    monkeypatch.setattr(particles, "HEAVY_FACES", 1000)
    monkeypatch.setattr(heavy, "LOWEST_SAMPLE", 50_000)
    monkeypatch.setattr(trimesh.Trimesh, "convex_hull", property(lambda mesh: pytest.fail("hull computed")))
    heavy_start = particles.initial_particles(np.random.default_rng(3), 40, [ObjectModel(6, ball)], table, "6dof")
    assert np.allclose(heavy_start, light, atol=1e-12)  # every vertex searched: the hull's lowest point


def test_a_heavy_model_is_named_where_a_frame_announces_it_and_a_light_frame_starts_nothing(monkeypatch, capfd):
    import subprocess

    from workbench.meshes import heavy
    from workbench.problem.scene import ObjectModel

    ball = ObjectModel(6, trimesh.creation.icosphere(5), source=Path("models/obj_000006.ply"))  # 20,480 faces
    box = ObjectModel(5, trimesh.creation.box())
    assert heavy.heavy_models([ball, box]) == ""
    monkeypatch.setattr(heavy, "HEAVY_FACES", 10_000)
    assert heavy.heavy_models([box, ball]) == "obj_000006.ply (20k faces)"
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: pytest.fail("an announcing process for light models"))
    with heavy.announced_if(heavy.heavy_models([box]), "estimating scene 0 frame 0"):
        pass
    assert capfd.readouterr().err == ""


def test_a_heavy_model_is_drawn_from_its_render_mesh_a_light_one_from_itself(monkeypatch):
    from types import SimpleNamespace

    from workbench.app.engine import observation
    from workbench.problem.scene import ObjectModel

    ball = trimesh.creation.icosphere(5, radius=0.05)  # 20,480 faces: "heavy" below
    render = trimesh.creation.icosphere(2, radius=0.05)  # what the cache holds for it: 320 faces
    box = trimesh.creation.box(extents=(0.1, 0.06, 0.02))
    problem = SimpleNamespace(models=[ObjectModel(6, ball), ObjectModel(5, box)])
    calls = []
    monkeypatch.setattr(observation, "HEAVY_FACES", 10_000)
    monkeypatch.setattr("workbench.evaluation.local.prepare_meshes", lambda pr: calls.append("prepare"))
    monkeypatch.setattr("workbench.inference.search.geometry.search_mesh",
                        lambda m, pr: calls.append(m.obj_id) or render)
    drawn_ball, drawn_box = observation.object_meshes(problem)
    assert calls == ["prepare", 6]  # simplified (or read from the cache) once, before anything is drawn
    assert len(drawn_ball.faces) == 20_480 and len(drawn_ball.solid[1]) == 320  # never the model's faces
    assert np.array_equal(drawn_ball.edges, observation.outline_edges(render.vertices, render.faces))
    assert np.array_equal(drawn_ball.cloud_edges, observation.cloud_outline(render))
    assert drawn_box.solid is None  # a light model as it always was
    assert np.array_equal(drawn_box.edges, observation.outline_edges(box.vertices, box.faces))
    calls.clear()
    observation.object_meshes(SimpleNamespace(models=[ObjectModel(5, box)]))
    assert calls == []


def test_a_pool_prepares_the_meshes_once_before_its_workers_start(monkeypatch):
    from workbench.evaluation import pool

    order = []
    monkeypatch.setattr(pool, "prepare_meshes", lambda problem: order.append("prepare"))
    monkeypatch.setattr(pool.PoolEvaluator, "_start", lambda self, i: order.append(f"worker {i}"))
    monkeypatch.setattr(pool.PoolEvaluator, "_hand_problem", lambda self, i: order.append(f"problem {i}"))
    pool.PoolEvaluator(object(), 3)
    # every worker started before the first is sent its problem: they import their libraries side by side
    assert order == ["prepare", "worker 0", "worker 1", "worker 2", "problem 0", "problem 1", "problem 2"]


def _hold_the_lock(key: str, folder: str, log: str, name: str, until: str) -> None:
    """Take the lock of ``key``, logging when trying, in and out; hold it until ``until`` is in the log."""
    import time
    from pathlib import Path

    from workbench.meshes.heavy import one_at_a_time

    def write(text: str) -> None:
        with open(log, "a") as f:
            f.write(text + "\n")

    write(f"{name} trying")
    with one_at_a_time(key, Path(folder)):
        write(f"{name} in")
        for _ in range(600):
            if not until or until in Path(log).read_text():
                break
            time.sleep(0.05)
        time.sleep(0.3)  # the other, blocked, has its chance to get in now if the lock did not hold it
        write(f"{name} out")


def test_processes_preparing_the_same_mesh_take_turns(tmp_path):
    import multiprocessing
    import time

    ctx = multiprocessing.get_context("spawn")
    log = tmp_path / "log"
    log.touch()
    first = ctx.Process(target=_hold_the_lock, args=("mesh-a", str(tmp_path), str(log), "first", "second trying"))
    second = ctx.Process(target=_hold_the_lock, args=("mesh-a", str(tmp_path), str(log), "second", ""))
    first.start()
    for _ in range(1200):  # the second starts once the first holds the lock
        if "first in" in log.read_text():
            break
        time.sleep(0.05)
    second.start()
    for p in (first, second):
        p.join(60)
    lines = [line for line in log.read_text().split("\n") if line and line != "first trying"]
    assert lines.index("first in") < lines.index("second trying") < lines.index("first out") < \
        lines.index("second in"), lines  # the second tried while the first held it, and waited its turn


def _stacked_scenes(seed: int, n: int, objects: int, spread: float) -> np.ndarray:
    """``n`` scenes (n, objects, 4, 4) of upright objects at random x, y within ``spread`` (m), each 5 cm above the
    one before."""
    scenes = np.repeat(np.eye(4)[None, None], n, axis=0).repeat(objects, axis=1)
    scenes[:, :, :2, 3] = np.random.default_rng(seed).uniform(-spread, spread, (n, objects, 2))
    scenes[:, :, 2, 3] = 0.05 * np.arange(1, objects + 1)
    return scenes


def _fresh_pool_evaluation(problem, scenes: np.ndarray):
    """``scenes`` evaluated by a new pool of 2 workers for ``problem``."""
    from workbench.evaluation import make_evaluator

    fresh = make_evaluator(problem, 2)
    try:
        return fresh.evaluate(scenes)
    finally:
        fresh.close()


@pytest.mark.slow
def test_a_runs_frames_share_one_pool_and_a_frame_evaluates_as_on_a_fresh_one(tmp_path):
    """``estimate`` over several frames starts its workers once (``run.runner.FramePool``): each later frame
    retargets them, and what a frame's hypotheses evaluate to does not depend on the frames before."""
    from workbench.problem.build import load_bop_problem
    from workbench.run.runner import FramePool
    from workbench.synth import make_scenes

    make_scenes(tmp_path / "ds", ["touching", "three"], 1, seed=2, width=320, height=240, sensor="kinect-like")
    (_, first), (_, second) = (load_bop_problem(tmp_path / "ds", s, 0) for s in (0, 1))
    scenes = _stacked_scenes(0, 6, second.n_objects, 0.1)
    pool = FramePool(workers=2, max_retries=0)
    try:
        lent = pool(first)
        lent.evaluate(scenes[:, :first.n_objects])
        lent.close()  # the frame is done: the workers stay
        pids = pool.evaluator.pids
        again = pool(second)
        assert pool.evaluator.pids == pids
        shared = again.evaluate(scenes)
    finally:
        pool.close()
    alone = _fresh_pool_evaluation(second, scenes)
    assert np.array_equal(shared.projected, alone.projected) and np.array_equal(shared.loglik, alone.loglik)


@pytest.mark.slow
def test_a_sequences_next_frame_keeps_the_workers_models_and_evaluates_as_a_fresh_pool(tmp_path):
    """A tracked sequence's next frame has the same objects: the pool sends it without their meshes and each worker
    keeps the ones it holds. What the frame's hypotheses evaluate to is what a fresh pool on it gives, and its new
    depth is the one scored."""
    from dataclasses import replace

    from workbench.evaluation import make_evaluator
    from workbench.problem.build import load_bop_problem
    from workbench.synth import make_scenes

    make_scenes(tmp_path / "ds", ["touching"], 1, seed=3, width=320, height=240, sensor="kinect-like")
    _, first = load_bop_problem(tmp_path / "ds", 0, 0)
    second = replace(first, observed=np.where(first.observed > 0, first.observed + 0.01, 0).astype(np.float32))
    scenes = _stacked_scenes(1, 5, first.n_objects, 0.05)
    pool = make_evaluator(first, 2)
    try:
        before = pool.evaluate(scenes)
        pool.retarget(second)
        after = pool.evaluate(scenes)
    finally:
        pool.close()
    alone = _fresh_pool_evaluation(second, scenes)
    assert np.array_equal(after.projected, alone.projected) and np.array_equal(after.loglik, alone.loglik)
    assert not np.array_equal(after.loglik, before.loglik)  # the second frame's depth, not the first's
