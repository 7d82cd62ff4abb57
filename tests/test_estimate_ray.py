"""`--engine ray` on a real Ray cluster started inside the test (2 CPUs, one head node; no mocks): a
frame's result does not depend on the engine, a killed worker is survived, `--resume` skips finished frames, a bad
frame is reported while the others go on, and a missing Ray says how to install it."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from workbench.cli import main
from workbench.evaluation import ChunkedEvaluator, PoolEvaluator, WorkerCrashed
from workbench.evaluation.ray import RayConfig, RayEvaluator
from workbench.problem.build import load_bop_problem
from workbench.synth import make_scenes

pytestmark = pytest.mark.slow  # needs Ray, pybullet and OpenGL

FAST = ("--particles", "16", "--iterations", "3", "--workers", "2")
FRAMES = [(0, 0), (1, 0), (2, 0)]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Three generated frames of two touching boxes (320x240, to stay quick)."""
    out = tmp_path_factory.mktemp("ray-touching")
    make_scenes(out, ["touching"], len(FRAMES), seed=5, width=320, height=240, sensor="kinect-like")
    return out


@pytest.fixture(scope="module")
def local_lines(dataset, tmp_path_factory) -> list[str]:
    """The reference: the results CSV of `--engine local` (a pool of 2 worker processes per frame)."""
    out = tmp_path_factory.mktemp("local") / "local.csv"
    assert main(["estimate", str(dataset), *FAST, "--out", str(out)]) == 0
    return out.read_text().splitlines()


def _without_time(lines: list[str]) -> list[str]:
    """Everything but the time column: scene, image, object, score, R, t as the CSV prints them (12 significant
    digits: R to ~1e-12, t to ~1e-9 mm)."""
    return [line.rsplit(",", 1)[0] for line in lines]


def _estimate_on_ray(cluster, dataset, out, *extra) -> int:
    return main(["estimate", str(dataset), *FAST, "--out", str(out), "--engine", "ray", "--ray-address", cluster,
                 *extra])


def test_local_and_ray_runs_agree(cluster, dataset, local_lines, tmp_path):
    out = tmp_path / "ray.csv"
    assert _estimate_on_ray(cluster, dataset, out) == 0
    lines = out.read_text().splitlines()
    # Same frames, same order (sorted by frame although the tasks finish in any order) and the same estimates to
    # the last printed digit: frame tasks split each batch as the local pool does, and the seed is per run.
    assert len(_objects(lines)) == 2 * len(FRAMES)  # every object of every frame (with its modes' rows)
    assert _without_time(lines) == _without_time(local_lines)


def _objects(lines: list[str]) -> set[tuple[str, str, str]]:
    """(scene, image, object) of a results CSV's rows (each object may have several: its posterior's modes)."""
    return {tuple(line.split(",")[:3]) for line in lines[1:]}


def _frame_task_pids() -> list[int]:
    """Ray workers running a frame task now (Ray titles a busy worker process ray::<task name>)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if (entry / "cmdline").read_bytes().startswith(b"ray::estimate_frame_task"):
                    pids.append(int(entry.name))
            except OSError:  # gone meanwhile
                pass
    return pids


def _run_killing_one_frame_task(cluster, dataset, out, *extra) -> int:
    """Estimate on Ray while SIGKILLing the first worker seen running a frame task -> the exit code."""
    killed: list[int] = []
    codes: list[int] = []
    run = threading.Thread(target=lambda: codes.append(_estimate_on_ray(cluster, dataset, out, *extra)))
    run.start()
    while run.is_alive() and not killed:
        pids = _frame_task_pids()
        if pids:
            os.kill(pids[0], signal.SIGKILL)
            killed.append(pids[0])
        time.sleep(0.02)
    run.join(timeout=300)
    assert killed, "no frame task was seen running: the test killed nothing"
    return codes[0]


def test_a_worker_killed_mid_run_is_survived_with_every_frame_written(cluster, dataset, local_lines, tmp_path,
                                                                     capsys):
    out = tmp_path / "ray.csv"
    assert _run_killing_one_frame_task(cluster, dataset, out) == 0
    # The killed frame ran again from scratch, on another worker, to the same result.
    assert _without_time(out.read_text().splitlines()) == _without_time(local_lines)

    # Without retries the same kill loses that frame, which is reported; the others are written all the same.
    out = tmp_path / "no-retries.csv"
    assert _run_killing_one_frame_task(cluster, dataset, out, "--max-retries", "0") == 1
    err = capsys.readouterr().err
    assert "its worker died 1 time(s)" in err and "1 of 3 frame(s) failed" in err
    lines = out.read_text().splitlines()
    assert len(_objects(lines)) == 2 * (len(FRAMES) - 1) and set(_without_time(lines)) < set(_without_time(local_lines))


def test_resume_skips_finished_frames(cluster, dataset, local_lines, tmp_path, capsys):
    out = tmp_path / "ray.csv"
    kept = [line for line in local_lines if not line.startswith("1,")]  # the header, scenes 0 and 2
    out.write_text("\n".join(kept) + "\n")
    assert _estimate_on_ray(cluster, dataset, out, "--resume") == 0
    assert "2 of 3 frame(s) already" in capsys.readouterr().err
    lines = out.read_text().splitlines()
    # The frames already there keep their lines byte for byte (their time column too: they were not run again).
    assert [line for line in lines if not line.startswith("1,")] == kept
    assert _without_time(lines) == _without_time(local_lines)


def test_a_bad_frame_is_reported_and_the_others_go_on(cluster, dataset, local_lines, tmp_path, capsys):
    broken = tmp_path / "broken"
    shutil.copytree(dataset, broken)
    (broken / "test" / "000001" / "depth" / "000000.png").write_bytes(b"not a png")
    out = tmp_path / "ray.csv"
    assert _estimate_on_ray(cluster, broken, out) == 1
    err = capsys.readouterr().err
    assert "scene 1 frame 0 failed" in err and "000001" in err and "000000.png" in err
    assert "1 of 3 frame(s) failed" in err and "Traceback" not in err
    good = [line for line in local_lines if not line.startswith("1,")]
    assert _without_time(out.read_text().splitlines()) == _without_time(good)


def test_missing_ray_says_how_to_install_it(dataset, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now fails as it does where Ray is not installed
    out = tmp_path / "r.csv"
    assert main(["estimate", str(dataset), *FAST, "--out", str(out), "--engine", "ray"]) == 2
    err = capsys.readouterr().err
    assert "workbench: error: --engine: ray is not installed" in err and "pip install 'workbench[ray]'" in err
    assert not out.exists()


def test_ray_address_needs_the_ray_engine_and_an_answering_head(dataset, tmp_path, capsys):
    out = str(tmp_path / "r.csv")
    assert main(["estimate", str(dataset), "--out", out, "--ray-address", "auto"]) == 2
    assert "--ray-address: joins a Ray cluster: use it with --engine ray" in capsys.readouterr().err
    # Ray alone would retry an unreachable head node for many minutes; the check answers at once.
    t0 = time.perf_counter()
    assert main(["estimate", str(dataset), "--out", out, "--engine", "ray", "--ray-address", "127.0.0.1:1"]) == 2
    assert "nothing answers at 127.0.0.1:1" in capsys.readouterr().err and time.perf_counter() - t0 < 30


PRIVATE_RAY = """
import ray
from workbench.evaluation.ray import RayConfig, connect, disconnect
connect(RayConfig(num_cpus=1))
print(ray.get_runtime_context().gcs_address, flush=True)
disconnect()
"""


def test_without_an_address_ray_starts_its_own_instance_and_joins_no_other(tmp_path):
    """RAY_ADDRESS names a cluster (here one that does not answer): Ray's own default would join it; the run starts
    a private Ray instead."""
    root = Path(__file__).resolve().parent.parent
    done = subprocess.run([sys.executable, "-c", PRIVATE_RAY], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "RAY_ADDRESS": "127.0.0.1:1", "PYTHONPATH": str(root)})
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() and not done.stdout.strip().endswith(":1"), done.stdout


def test_ray_evaluator_equals_the_local_pool(cluster, dataset):
    frame, problem = load_bop_problem(dataset, 0, 0)
    rng = np.random.default_rng(0)
    truth = np.linalg.inv(problem.camera.T_cam_world)[None] @ frame.gt_T_cam_obj  # (K, 4, 4) table frame
    hypotheses = np.repeat(truth[None], 9, axis=0)  # (9, K, 4, 4): the truth shifted by up to 2 cm
    hypotheses[:, :, :3, 3] += rng.uniform(-0.02, 0.02, size=hypotheses[:, :, :3, 3].shape)
    hypotheses[:, :, 2, 3] += 0.005  # lifted clear of the table

    evaluators = [RayEvaluator(problem, 2, RayConfig(address=cluster)), PoolEvaluator(problem, 2),
                  ChunkedEvaluator(problem, 2)]
    try:
        results = [e.evaluate(hypotheses) for e in evaluators]
        for other in results[1:]:
            assert np.array_equal(results[0].projected, other.projected)
            assert np.array_equal(results[0].loglik, other.loglik)
            assert np.array_equal(results[0].status, other.status)
        # The search's candidate fits (``Evaluator.map``) give the same on the actors as on the pool and here.
        from workbench.inference.search.datadriven import fit_scores
        from workbench.inference.search.scenepoints import model_samples

        calls = [(hypotheses[:n, 0], model_samples(problem.models[0].mesh)) for n in (2, 5, 1)]
        mapped = [e.map(fit_scores, calls) for e in evaluators]
        assert [len(a) for a in mapped[0]] == [2, 5, 1]
        for other in mapped[1:]:
            assert all(np.array_equal(a, b) for a, b in zip(mapped[0], other))
        # An actor that dies is a crashed worker, as in the local pool: the app rebuilds its evaluator on it.
        ray_evaluator = evaluators[0]
        os.kill(ray_evaluator.pids[1], signal.SIGKILL)
        with pytest.raises(WorkerCrashed):
            ray_evaluator.evaluate(hypotheses)
    finally:
        for e in evaluators:
            e.close()


def test_bench_on_ray_reports_what_the_local_engine_reports(cluster, dataset, tmp_path):
    import json

    bench = ["bench", str(dataset), "--methods", "icp,pipf", "--particles", "16", "--iterations", "2"]
    assert main([*bench, "--out", str(tmp_path / "local")]) == 0
    assert main([*bench, "--out", str(tmp_path / "ray"), "--engine", "ray", "--ray-address", cluster]) == 0
    local, on_ray = (json.loads((tmp_path / d / "report.json").read_text()) for d in ("local", "ray"))
    assert on_ray["engine"] == "ray" and on_ray["failed_frames"] == []
    assert len(on_ray["objects"]) == 2 * 2 * len(FRAMES)  # 2 objects x 2 methods per frame
    # Per-object errors are computed from the estimates, which agree bit for bit: equal to the last digit.
    assert on_ray["objects"] == local["objects"] and on_ray["table1"] == local["table1"]
    for method in ("icp", "pipf"):
        lines = [(tmp_path / d / f"results_{method}.csv").read_text().splitlines() for d in ("local", "ray")]
        assert _without_time(lines[0]) == _without_time(lines[1])


def test_serve_evaluates_on_ray_actors_and_survives_a_dead_one(cluster):
    import socket

    from workbench.app import protocol as p
    from workbench.app.ui.server import serve
    from workbench.inference.config import EstimatorConfig

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    handle = serve(demo=True, block=False, port=port, workers=2, config=EstimatorConfig(particles=16, iterations=50),
                   ray=RayConfig(address=cluster))
    app = handle.app
    try:
        assert app.wait_for(lambda s: s.view is not None and len(s.worker_pids) == 2, 180), app.state.failures
        actors = list(app.state.worker_pids)
        # The evaluation runs in the cluster's actor processes: Ray titles them ray::_EvaluatorActor.
        assert all(Path(f"/proc/{pid}/cmdline").read_bytes().startswith(b"ray::_EvaluatorActor") for pid in actors)
        app.send(p.Step())
        assert app.wait_for(lambda s: s.iteration == 0, 120), app.state.failures
        os.kill(actors[0], signal.SIGKILL)
        app.send(p.Step())
        assert app.wait_for(lambda s: s.iteration == 1, 120), app.state.failures
        assert app.state.restarts == 1 and actors[0] not in app.state.worker_pids
        assert not app.state.failures
    finally:
        handle.stop()
