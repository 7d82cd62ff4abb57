"""`workbench track --engine ray` on a real Ray cluster started inside the test (2 CPUs, one head
node; no mocks), as tests/test_estimate_ray.py does for `estimate`: each sequence is one task, the sequences run side by
side, the results equal the local engine's, and a sequence that fails is reported while the others are written."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("ray")

from workbench.cli import main  # noqa: E402
from workbench.synth.sequence import make_sequences  # noqa: E402

pytestmark = pytest.mark.slow  # needs Ray, pybullet and OpenGL

FAST = ("--particles", "32", "--iterations", "4", "--workers", "2", "--track-particles", "24")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Two generated sequences of three frames (two touching boxes, the camera on a 4 degree arc; 320x240)."""
    out = tmp_path_factory.mktemp("track-ray")
    make_sequences(out, ["touching"], 2, 3, seed=0, width=320, height=240, arc_deg=4.0, sensor="kinect-like")
    return out


def _without_time(lines: list[str]) -> list[str]:
    return [line.rsplit(",", 1)[0] for line in lines]


def _track(dataset, out, *extra) -> int:
    return main(["track", str(dataset), "--scene", "0", "1", *FAST, "--out", str(out), *extra])


def test_sequences_on_ray_run_side_by_side_and_agree_with_the_local_engine(cluster, dataset, tmp_path, capsys):
    local, on_ray = tmp_path / "local.csv", tmp_path / "ray.csv"
    assert _track(dataset, local) == 0
    capsys.readouterr()
    assert _track(dataset, on_ray, "--engine", "ray", "--ray-address", cluster) == 0
    err = capsys.readouterr().err
    lines = on_ray.read_text().splitlines()
    # Every frame of both sequences, each frame's line, and the same estimates to the last printed digit as the
    # local engine's: a sequence task splits each batch as the local pool does.
    said = all(f"scene {s} frame {i}: " in err for s in (0, 1) for i in (0, 1, 2))
    assert (said, _without_time(lines)) == (True, _without_time(local.read_text().splitlines()))


def test_a_broken_frame_of_one_sequence_is_refused_before_any_sequence_runs_on_ray(cluster, dataset, tmp_path,
                                                                                  capsys):
    """Every frame's depth is read before the first frame runs (issue 67), on Ray as locally: a damaged depth PNG in
    one sequence ends the command before any work, naming the file, and writes no results."""
    broken = tmp_path / "broken"
    import shutil

    shutil.copytree(dataset, broken)
    (broken / "test" / "000001" / "depth" / "000001.png").write_bytes(b"not a png")
    out = tmp_path / "ray.csv"
    code = _track(broken, out, "--engine", "ray", "--ray-address", cluster)
    err = capsys.readouterr().err
    assert code == 2 and "000001.png" in err and "workbench: error:" in err, err
    assert not out.exists()
