"""The limits of the one JSON reader and the one image reader every input goes through (issue 67): a file nested
200,000 levels deep, a number of 400 or 5000 digits, an image of 20000 x 20000 pixels each end in
`workbench: error: FILE: problem` with exit code 2, never a traceback or a raw library warning."""

from __future__ import annotations

import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from workbench.cli import DEMO_DATASET, main
from workbench.errors import InputError
from workbench.io import bop
from workbench.io.readers import MAX_JSON_DEPTH, MAX_NUMBER_CHARS, parse_json, read_json


@pytest.fixture
def demo(tmp_path) -> Path:
    out = tmp_path / "demo"
    shutil.copytree(DEMO_DATASET, out)
    return out


def _refused(capsys, argv, *words) -> str:
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("workbench: error: ") and "Traceback" not in err, err
    for w in words:
        assert w in err, err
    return err


@pytest.mark.parametrize("text, words", [
    ("[" * 200_000 + "]" * 200_000, "nested deeper"),
    ("[" * (MAX_JSON_DEPTH + 1) + "]" * (MAX_JSON_DEPTH + 1), f"more than {MAX_JSON_DEPTH} levels"),
    ("[" + "1" * 400 + "]", "number of 400 characters"),
    ("[" + "7" * 5000 + "]", "number of 5000 characters"),
    ("[0." + "1" * 5000 + "]", "number of 5002 characters"),
    ("\ufeff{}", "BOM"),
])
def test_json_beyond_the_limits_is_refused_naming_the_file(text, words):
    with pytest.raises(InputError, match=words) as caught:
        parse_json(text.encode(), "f.json")
    assert caught.value.path == "f.json"


def test_json_within_the_limits_is_read_as_json():
    deep = "[" * MAX_JSON_DEPTH + "]" * MAX_JSON_DEPTH
    assert parse_json(deep.encode(), "f.json") is not None
    long_number = "1" * MAX_NUMBER_CHARS
    assert parse_json(f'{{"a": {long_number}, "b": NaN, "c": 1e999}}', "f.json")["a"] == int(long_number)


def test_a_json_file_too_large_is_refused_from_its_size(tmp_path, monkeypatch):
    import workbench.io.readers as readers

    path = tmp_path / "big.json"
    path.write_text("[" + "0," * 600 + "0]")
    monkeypatch.setattr(readers, "MAX_JSON_BYTES", 1000)
    with pytest.raises(InputError, match="more than any input"):
        read_json(path)


@pytest.mark.parametrize("file, key, digits", [
    ("scene_camera.json", "cam_K", 400),
    ("scene_camera.json", "cam_t_w2c", 5000),
    ("scene_gt.json", "cam_t_m2c", 400),
])
def test_a_huge_integer_in_a_dataset_file_is_an_input_error(demo, tmp_path, capsys, file, key, digits):
    path = demo / "test" / "000000" / file
    # The first number of the list replaced by a whole number of ``digits`` digits.
    path.write_text(re.sub(rf'"{key}": \[\s*[^,\]]*', f'"{key}": [' + "9" * digits, path.read_text(), count=1))
    _refused(capsys, ["estimate", demo, "--out", tmp_path / "r.csv"], file, f"number of {digits} characters")
    assert not (tmp_path / "r.csv").exists()


@pytest.mark.parametrize("file", ["test/000000/scene_camera.json", "models/models_info.json"])
def test_json_nested_200000_levels_in_a_dataset_file_is_an_input_error(demo, tmp_path, capsys, file):
    (demo / file).write_text('{"0": ' + "[" * 200_000 + "]" * 200_000 + "}")
    _refused(capsys, ["estimate", demo, "--out", tmp_path / "r.csv"], Path(file).name, "nested deeper")


def test_a_session_nested_200000_levels_is_an_input_error(tmp_path, capsys):
    session = tmp_path / "s.json"
    session.write_text('{"kind": ' + "[" * 200_000 + "]" * 200_000 + "}")
    _refused(capsys, ["serve", "--session", session], "s.json", "corrupt session file", "nested deeper")


def _png_of_size(width: int, height: int) -> bytes:
    """A 16-bit PNG whose header says ``width`` x ``height`` (its pixels are a 2 x 2 image's: only the header is
    meant to be read)."""
    import io

    buf = io.BytesIO()
    Image.fromarray(np.full((2, 2), 1000, np.uint16)).save(buf, format="PNG")
    data = bytearray(buf.getvalue())
    data[16:24] = width.to_bytes(4, "big") + height.to_bytes(4, "big")
    return bytes(data)


@pytest.mark.parametrize("side", [20000, 13000, 5001])
def test_a_depth_image_of_too_many_pixels_is_refused_from_its_header(tmp_path, side):
    path = tmp_path / "d.png"
    path.write_bytes(_png_of_size(side, side))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no raw library warning either
        with pytest.raises(InputError, match=f"{side} x {side} pixels"):
            bop.read_depth_png(path)


def test_a_depth_image_over_pils_own_limit_in_the_dataset_is_an_input_error(demo, tmp_path, capsys):
    (demo / "test" / "000000" / "depth" / "000000.png").write_bytes(_png_of_size(20000, 20000))
    _refused(capsys, ["estimate", demo, "--out", tmp_path / "r.csv"], "000000.png", "20000 x 20000 pixels")


def test_an_image_that_is_no_png_is_still_read_through_pil(tmp_path):
    path = tmp_path / "c.jpg"
    Image.fromarray(np.zeros((4, 6, 3), np.uint8)).save(path)
    assert bop.image_size(path) == (6, 4) and bop.read_rgb(path).shape == (4, 6, 3)
    path.write_bytes(b"not an image")
    with pytest.raises(InputError, match="corrupt or unreadable"):
        bop.read_rgb(path)


def test_a_mesh_wound_inside_out_is_turned_right_side_out_and_named_once(tmp_path, caplog):
    import trimesh

    box = trimesh.creation.box((50.0, 60.0, 70.0))  # mm, as BOP's models
    box.invert()
    path = tmp_path / "obj_000001.ply"
    box.export(path)
    with caplog.at_level("WARNING"):
        first, again = bop.read_mesh(path, 1e-3), bop.read_mesh(path, 1e-3)
    assert first.volume == pytest.approx(50 * 60 * 70 * 1e-9) and again.volume > 0
    warned = [r.getMessage() for r in caplog.records if "inside out" in r.getMessage()]
    assert len(warned) == 1 and str(path) in warned[0], warned


@pytest.mark.parametrize("argv, words", [
    (["--iterations", "100000"], "--iterations: must be a whole number from 0 to 10000"),
    (["--max-retries", "1000"], "--max-retries: must be a whole number from 0 to 100"),
    (["--max-render-pixels", "100000000"], "--max-render-pixels: must be a whole number from 64 to 25000000"),
    # ~1.3 TB by the measured ~14 bytes per particle and pixel: more than any machine here has free
    (["--particles", "100000", "--max-render-pixels", "1000000"], "would need about"),
    (["--posterior", "p.json", "--no-settle"], "--posterior: the posterior is made while the estimate is settled"),
    (["--posterior", "p.json", "--proposals", "paper"], "which --proposals paper leaves out"),
])
def test_counts_beyond_their_bounds_and_outputs_never_made_are_refused_before_any_work(demo, tmp_path, capsys,
                                                                                     monkeypatch, argv, words):
    monkeypatch.chdir(tmp_path)
    _refused(capsys, ["estimate", demo, "--out", tmp_path / "r.csv", *argv], words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo"]


@pytest.mark.parametrize("argv, words", [
    (["--track-particles", "10000000"], "--track-particles: must be a whole number from 1 to 100000"),
    (["--track-iterations", "100000"], "--track-iterations: must be a whole number from 1 to 1000"),
    (["--track-particles", "100000", "--max-render-pixels", "1000000"], "--track-particles: 100000 particles"),
])
def test_track_counts_are_bounded_before_the_first_frame(demo, tmp_path, capsys, argv, words):
    _refused(capsys, ["track", demo, "--scene", "0", "--out", tmp_path / "r.csv", *argv], words)
    assert not (tmp_path / "r.csv").exists()


def test_serve_names_the_scene_of_a_frame_it_lacks(demo, capsys):
    _refused(capsys, ["serve", demo, "--frame", "99"], "no frame 99 in scene 0")


def _workers_started(pid: int, settle_s: float = 3.0, timeout_s: float = 120.0) -> None:
    """Wait until ``pid`` has its evaluation workers (spawned processes) and their number held for ``settle_s``: a
    worker killed while Python's spawn still reads its start-up data prints that module's traceback, which is no
    part of what this test checks."""
    import time

    def workers() -> int:
        try:
            kids = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
        except OSError:
            return 0
        return sum(b"spawn_main" in Path(f"/proc/{k}/cmdline").read_bytes() for k in kids
                   if Path(f"/proc/{k}/cmdline").exists())

    end, last, since = time.monotonic() + timeout_s, -1, time.monotonic()
    while time.monotonic() < end:
        now = workers()
        if now != last:
            last, since = now, time.monotonic()
        elif now > 0 and time.monotonic() - since >= settle_s:
            return
        time.sleep(0.2)


@pytest.mark.slow  # starts the browser workbench
def test_serve_on_the_network_warns_what_a_visitor_can_do_and_sigterm_ends_it_with_143(tmp_path):
    import os
    import signal
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent
    server = subprocess.Popen([sys.executable, "-m", "workbench.cli", "serve", "--demo", "--host", "0.0.0.0",
                               "--port", "18397", "--sessions-dir", str(tmp_path / "s")],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                              env={**os.environ, "PYTHONPATH": str(root), "WORKBENCH_HOME": str(tmp_path / "home")})
    try:
        for line in server.stdout:
            if "serving" in line:
                break
        _workers_started(server.pid)
        server.send_signal(signal.SIGTERM)
        _, err = server.communicate(timeout=120)
    finally:
        server.kill()
    assert server.returncode == 143, err
    assert "WARNING: serving on 0.0.0.0" in err and "labels" in err and "sessions" in err, err
    assert "Traceback" not in err


def test_a_plain_frames_npy_depth_of_too_many_numbers_is_refused_from_its_header(tmp_path):
    from workbench.io.plainframe import _read_depth

    path = tmp_path / "d.npy"
    np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=(6000, 6000)).flush()  # sparse on disk
    with pytest.raises(InputError, match="6000 x 6000"):
        _read_depth(path, 1.0)
