"""The `workbench` command as a user runs it: a real subprocess."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from workbench.io.results import read_results_csv

pytestmark = pytest.mark.slow  # needs whole estimates: pybullet and OpenGL


def _workbench(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "workbench.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600, cwd=cwd)


def test_estimate_writes_a_bop_results_csv(touching_dataset, tmp_path):
    out, posterior = tmp_path / "results.csv", tmp_path / "posterior.json"
    run = _workbench("estimate", touching_dataset, "--particles", 32, "--iterations", 2, "--out", out,
                     "--posterior", posterior)
    assert run.returncode == 0, run.stderr
    assert "[posterior " in run.stderr  # the frame's line says what the posterior cost
    header = out.read_text().splitlines()[0]
    assert header == "scene_id,im_id,obj_id,score,R,t,time"
    rows = read_results_csv(out)
    # Each object's posterior modes as rows, the most likely first, their probabilities summing to 1 (given that it
    # was found: the chance that it is elsewhere is in the posterior file).
    objects = sorted({r.obj_id for r in rows})
    assert objects == sorted(int(i) for i in _gt_ids(touching_dataset))
    import json

    (frame,) = json.loads(posterior.read_text())["frames"]
    elsewhere = {o["obj_id"]: o["elsewhere"] for o in frame["objects"]}
    for obj_id in objects:
        scores = [r.score for r in rows if r.obj_id == obj_id]
        assert np.isclose(sum(scores), 1.0, atol=1e-5) and scores == sorted(scores, reverse=True)
        assert 0.0 < elsewhere[obj_id] < 0.5  # the estimate is where the depth shows it: no doubt to speak of
    for r in rows:
        R = r.T_cam_obj[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-5)
        assert 0.2 < r.T_cam_obj[2, 3] < 3.0  # in front of the camera, metres after reading mm
        assert 0.0 <= r.score <= 1.0 and r.time > 0
    # The posterior file: per frame its wall time and the sweep's share, per object the same modes as the rows.
    assert 0 < frame["posterior_seconds"] < frame["seconds"] == pytest.approx(rows[0].time, abs=2e-3)
    for o in frame["objects"]:
        scores = [r.score for r in rows if r.obj_id == o["obj_id"]]
        assert [m["probability"] for m in o["modes"]] == pytest.approx(scores, abs=1e-5)


def _gt_ids(dataset):
    import json

    gt = json.loads((dataset / "test" / "000000" / "scene_gt.json").read_text())
    return [o["obj_id"] for o in gt["0"]]


def test_missing_dataset_is_named(tmp_path):
    run = _workbench("estimate", tmp_path / "nowhere", "--out", tmp_path / "r.csv")
    assert run.returncode == 2
    assert "nowhere" in run.stderr and "Traceback" not in run.stderr
    assert not (tmp_path / "r.csv").exists()


def test_depth_scale_that_puts_the_table_100_m_away_is_caught(touching_dataset, tmp_path):
    import json
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(touching_dataset, bad)
    cam_path = bad / "test" / "000000" / "scene_camera.json"
    cam = json.loads(cam_path.read_text())
    cam["0"]["depth_scale"] *= 1000.0
    cam_path.write_text(json.dumps(cam))
    run = _workbench("estimate", bad, "--particles", 8, "--iterations", 1, "--out", tmp_path / "r.csv")
    assert run.returncode == 2
    assert "scene_camera.json" in run.stderr and "depth_scale" in run.stderr


def test_impossible_parameters_are_refused(touching_dataset, tmp_path):
    run = _workbench("estimate", touching_dataset, "--particles", 0, "--out", tmp_path / "r.csv")
    assert run.returncode == 2 and "particle" in run.stderr


def test_bench_speed_measures_a_named_dataset(touching_dataset, tmp_path):
    run = _workbench("bench", "--speed", touching_dataset, "--particles", 16, "--repeats", 1, "--workers", 1)
    assert run.returncode == 0, run.stderr
    assert f"bench --speed {touching_dataset}" in run.stdout
    rows = [line for line in run.stdout.splitlines() if line.startswith("| ") and "frame" not in line]
    assert len(rows) == 1 and float(rows[0].split("|")[5]) > 0  # one frame, evaluations/s measured
    assert "box (fills" in run.stdout  # the generated boxes collide as boxes, fit shown
    missing = _workbench("bench", "--speed", tmp_path / "nowhere")
    assert missing.returncode == 2 and "workbench: error:" in missing.stderr and "nowhere" in missing.stderr


def test_no_settle_keeps_the_estimate_as_physics_put_it():
    from workbench.cli import build_parser, estimator_config

    parser = build_parser()
    assert estimator_config(parser.parse_args(["estimate", "ds"])).settle_shift > 0
    assert estimator_config(parser.parse_args(["estimate", "ds", "--no-settle"])).settle_shift == 0
    assert estimator_config(parser.parse_args(["estimate", "ds"])).leaning
    assert not estimator_config(parser.parse_args(["track", "ds", "--scene", "1", "--no-leaning"])).leaning


@pytest.mark.parametrize("command", [["estimate", "assets/demo"], ["track", "assets/demo", "--scene", "0"],
                                     ["serve", "--demo", "--port", "1"], ["bench", "--speed"]])
def test_missing_mujoco_says_how_to_install_it_before_any_work(command, tmp_path, monkeypatch, capsys):
    from workbench.cli import main

    monkeypatch.setitem(sys.modules, "mujoco", None)  # `import mujoco` now fails as where it is not installed
    monkeypatch.chdir(tmp_path)  # nothing may be written: any file here would be work begun
    demo = str(Path(__file__).resolve().parent.parent / "assets" / "demo")
    assert main([demo if a == "assets/demo" else a for a in command] + ["--physics", "mujoco"]) == 2
    err = capsys.readouterr().err
    assert "workbench: error: --physics: mujoco is not installed" in err and "pip install 'workbench[mujoco]'" in err
    assert list(tmp_path.iterdir()) == []
