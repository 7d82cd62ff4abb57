"""BOP datasets and plain frames: save -> load round trips, and every bad input names its file."""

from __future__ import annotations

import json
import logging
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from workbench.errors import InputError
from workbench.geometry import make_pose, rot_x, rot_z
from workbench.io import bop
from workbench.io.plainframe import load_plain_frame
from workbench.io.results import ResultRow, read_results_csv, write_results_csv

W, H = 64, 48
K = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
T_CAM_WORLD = make_pose(rot_x(-2.2), [0.01, 0.05, 0.8])
GT = [(1, make_pose(rot_z(0.3), [0.02, -0.01, 0.75])), (2, make_pose(rot_x(1.0), [-0.05, 0.03, 0.82]))]


def scene_depth() -> np.ndarray:
    """(H, W) metres: a tilted plane 0.7-0.9 m away with a few holes."""
    v, u = np.mgrid[0:H, 0:W]
    depth = 0.7 + 0.2 * v / H + 0.001 * u
    depth[5, 7] = depth[20, 30] = 0.0
    return depth


def make_dataset(root: Path) -> Path:
    """Two objects, scene 3 with images 0 and 4 (each with rgb), in BOP layout."""
    box = trimesh.creation.box((0.05, 0.08, 0.12))
    cyl = trimesh.creation.cylinder(radius=0.03, height=0.1)
    flip = make_pose(rot_z(np.pi), [0.0, 0.0, 0.0])
    bop.save_models(root, {1: box, 2: cyl}, symmetries={1: np.stack([np.eye(4), flip])})
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 1] = 200
    for im_id in (0, 4):
        bop.save_frame(
            root, 3, im_id, scene_depth(), K, T_cam_world=T_CAM_WORLD, gt=GT,
            gt_info=[{"visib_fract": 0.9}, {"visib_fract": 0.5}], rgb=rgb,
        )
    return root


def edit_json(path: Path, edit) -> None:
    content = json.loads(path.read_text())
    edit(content)
    path.write_text(json.dumps(content))


@pytest.fixture
def dataset(tmp_path) -> Path:
    return make_dataset(tmp_path / "ds")


def scene(dataset: Path) -> Path:
    return dataset / "test" / "000003"


# ---------------------------------------------------------------------------------------------------- round trips


def test_models_round_trip_millimetres_on_disk(dataset):
    raw = trimesh.load(dataset / "models" / "obj_000001.ply", force="mesh")
    np.testing.assert_allclose(np.sort(raw.extents), [50.0, 80.0, 120.0], rtol=1e-6)
    info = json.loads((dataset / "models" / "models_info.json").read_text())
    assert info["1"]["diameter"] == pytest.approx(np.linalg.norm([50, 80, 120]), rel=1e-6)
    assert info["1"]["min_x"] == pytest.approx(-25.0) and info["2"]["size_z"] == pytest.approx(100.0)

    models = bop.load_models(dataset)
    assert sorted(models) == [1, 2]
    np.testing.assert_allclose(models[1].mesh.extents, [0.05, 0.08, 0.12], rtol=1e-6)
    assert models[1].mesh.is_watertight and models[1].mass == pytest.approx(0.05 * 0.08 * 0.12 * 1000.0)
    np.testing.assert_allclose(models[1].symmetries[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(models[1].symmetries[1], make_pose(rot_z(np.pi), [0, 0, 0]), atol=1e-9)
    assert models[2].symmetries.shape == (1, 4, 4)
    assert set(bop.load_models(dataset, obj_ids=[2], friction=0.3)) == {2}


def test_continuous_symmetry_becomes_rotations_about_its_axis(dataset):
    path = dataset / "models" / "models_info.json"
    edit_json(path, lambda c: c["2"].update(symmetries_continuous=[{"axis": [0, 0, 1], "offset": [0, 0, 10]}]))
    syms = bop.load_models(dataset, [2])[2].symmetries
    assert syms.shape == (bop.CONTINUOUS_SYMMETRY_STEPS, 4, 4)
    # Each keeps the axis point (0, 0, 10 mm) fixed and turns about z.
    np.testing.assert_allclose(syms[:, :3, :3] @ [0, 0, 0.01] + syms[:, :3, 3], np.tile([0, 0, 0.01], (36, 1)),
                               atol=1e-12)
    np.testing.assert_allclose(syms[5, :3, :3], rot_z(5 * 2 * np.pi / 36), atol=1e-12)


def test_open_mesh_warns_naming_the_file(dataset, caplog):
    open_box = trimesh.creation.box((0.05, 0.05, 0.05))
    open_box.update_faces(np.arange(len(open_box.faces)) != 0)
    bop.save_models(dataset, {3: open_box})
    with caplog.at_level(logging.WARNING):
        model = bop.load_models(dataset, [3])[3]
    assert "obj_000003.ply" in caplog.text and "not watertight" in caplog.text
    assert model.mass == pytest.approx(0.05**3 * 1000.0, rel=1e-6)
    caplog.clear()
    with caplog.at_level(logging.WARNING):  # every frame of a dataset loads its models again: said once is enough
        bop.load_models(dataset, [3])
    assert "not watertight" not in caplog.text


def test_frames_round_trip(dataset):
    assert bop.list_frames(dataset) == [(3, 0), (3, 4)]
    frame = bop.load_frame(dataset, 3, 4)
    assert frame.depth.dtype == np.float32 and frame.depth.shape == (H, W)
    # depth_scale 0.1: stored in steps of 0.1 mm.
    np.testing.assert_allclose(frame.depth, scene_depth(), atol=0.05e-3 + 1e-7)
    assert frame.depth[5, 7] == 0.0
    np.testing.assert_allclose(frame.camera.K, K)
    assert (frame.camera.width, frame.camera.height) == (W, H)
    np.testing.assert_allclose(frame.camera.T_cam_world, T_CAM_WORLD, atol=1e-9)
    assert frame.object_ids == [1, 2] and (frame.scene_id, frame.im_id) == (3, 4)
    np.testing.assert_allclose(frame.gt_T_cam_obj, np.stack([T for _, T in GT]), atol=1e-9)
    assert frame.rgb.shape == (H, W, 3) and frame.rgb[0, 0, 1] == 200
    info = json.loads((scene(dataset) / "scene_gt_info.json").read_text())
    assert list(info) == ["0", "4"] and info["4"][1]["visib_fract"] == 0.5


def test_a_scenes_files_are_parsed_once_while_their_bytes_stay_the_same(dataset, monkeypatch):
    from workbench.io import readers

    parsed, parse = [], readers.parse_json
    monkeypatch.setattr(readers, "parse_json", lambda data, path: parsed.append(Path(path).name) or parse(data, path))
    bop.load_frame(dataset, 3, 0)
    assert bop.load_frame(dataset, 3, 4).object_ids == [1, 2]
    assert parsed.count("scene_gt.json") == 1 and parsed.count("scene_camera.json") == 1
    # Rewritten in place at once, to the same size: the timestamps may not tell, the bytes do.
    edit_json(scene(dataset) / "scene_gt.json", lambda content: content["4"][0].update(obj_id=2))
    assert bop.load_frame(dataset, 3, 4).object_ids == [2, 2]
    assert parsed.count("scene_gt.json") == 2 and parsed.count("scene_camera.json") == 1


def test_objects_from_test_targets_when_ground_truth_is_withheld(dataset):
    (scene(dataset) / "scene_gt.json").unlink()
    with raises_on(scene(dataset), "--objects"):
        bop.load_frame(dataset, 3, 4)
    targets = [{"scene_id": 3, "im_id": 4, "obj_id": 2, "inst_count": 2}, {"scene_id": 3, "im_id": 0, "obj_id": 1}]
    (dataset / "test_targets_bop19.json").write_text(json.dumps(targets))
    frame = bop.load_frame(dataset, 3, 4)
    assert frame.object_ids == [2, 2] and frame.gt_T_cam_obj is None


def test_split_folder_and_requested_objects(dataset):
    frame = bop.load_frame(dataset / "test", 3, 0, object_ids=[2])
    assert frame.object_ids == [2]
    np.testing.assert_allclose(frame.gt_T_cam_obj[0], GT[1][1], atol=1e-9)
    assert bop.list_frames(dataset / "test") == bop.list_frames(dataset, split="test")


def test_results_csv_round_trip(tmp_path):
    rows = [ResultRow(3, 4, 1, 0.75, GT[0][1], 1.25), ResultRow(3, 4, 2, 0.5, GT[1][1], -1.0)]
    path = tmp_path / "res.csv"
    write_results_csv(path, rows)
    lines = path.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    assert lines[1].split(",")[5].split() == [f"{v:.12g}" for v in GT[0][1][:3, 3] * 1000]
    back = read_results_csv(path)
    for a, b in zip(rows, back):
        assert (a.scene_id, a.im_id, a.obj_id, a.score, a.time) == (b.scene_id, b.im_id, b.obj_id, b.score, b.time)
        np.testing.assert_allclose(a.T_cam_obj, b.T_cam_obj, atol=1e-9)


# ---------------------------------------------------------------------------------------------------- BOP errors


@contextmanager
def raises_on(path: Path, match: str):
    """The InputError must name ``path`` and say ``match``."""
    with pytest.raises(InputError, match=match) as info:
        yield
    assert info.value.path == str(path), info.value


def test_missing_files(dataset, tmp_path):
    with raises_on(tmp_path / "nope", "not found"):
        bop.load_frame(tmp_path / "nope", 3, 0)
    with raises_on(dataset / "test" / "000009", "scene 9 not found"):
        bop.load_frame(dataset, 9, 0)
    depth = scene(dataset) / "depth" / "000004.png"
    depth.unlink()
    with raises_on(depth, "not found"):
        bop.load_frame(dataset, 3, 4)
    (dataset / "models" / "obj_000002.ply").unlink()
    with raises_on(dataset / "models" / "obj_000002.ply", "not found"):
        bop.load_models(dataset)


def test_corrupt_files(dataset):
    cam = scene(dataset) / "scene_camera.json"
    good = cam.read_text()
    cam.write_text('{"0": {"cam_K": [1, 2')
    with raises_on(cam, "corrupt JSON"):
        bop.load_frame(dataset, 3, 0)
    cam.write_text(good)
    png = scene(dataset) / "depth" / "000004.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with raises_on(png, "corrupt"):
        bop.load_frame(dataset, 3, 4)
    ply = dataset / "models" / "obj_000001.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 3\n")
    with raises_on(ply, "corrupt|no triangles"):
        bop.load_models(dataset, [1])


def test_eight_bit_depth_is_refused(dataset):
    png = scene(dataset) / "depth" / "000000.png"
    Image.fromarray(np.full((H, W), 80, np.uint8)).save(png)
    with raises_on(png, "16-bit"):
        bop.load_frame(dataset, 3, 0)


def test_camera_problems(dataset):
    cam = scene(dataset) / "scene_camera.json"
    edit_json(cam, lambda c: c["0"].pop("cam_K"))
    with raises_on(cam, "no cam_K"):
        bop.load_frame(dataset, 3, 0)
    edit_json(cam, lambda c: c["4"].update(cam_K=[float("nan")] + c["4"]["cam_K"][1:]))
    with raises_on(cam, "NaN"):
        bop.load_frame(dataset, 3, 4)
    edit_json(cam, lambda c: c["4"].update(cam_K=[-60, 0, 31.5, 0, 60, 23.5, 0, 0, 1]))
    with raises_on(cam, "focal lengths must be positive"):
        bop.load_frame(dataset, 3, 4)
    # K of a 640x480 camera with a 64x48 depth image.
    edit_json(cam, lambda c: c["4"].update(cam_K=[600, 0, 319.5, 0, 600, 239.5, 0, 0, 1]))
    with raises_on(cam, "outside the 64x48 depth image"):
        bop.load_frame(dataset, 3, 4)


def test_depth_size_against_dataset_camera_file(dataset):
    (dataset / "camera.json").write_text(json.dumps({"width": 640, "height": 480, "fx": 600}))
    with raises_on(scene(dataset) / "depth" / "000000.png", "64x48 but camera.json says 640x480"):
        bop.load_frame(dataset, 3, 0)


def test_nan_in_ground_truth_pose(dataset):
    gt = scene(dataset) / "scene_gt.json"
    edit_json(gt, lambda c: c["0"][1].update(cam_t_m2c=[0, float("inf"), 800]))
    with raises_on(gt, "NaN or inf"):
        bop.load_frame(dataset, 3, 0)


def test_wrong_depth_scale_suggests_one(dataset):
    cam = scene(dataset) / "scene_camera.json"
    edit_json(cam, lambda c: c["0"].update(depth_scale=100.0))  # 1000 times too large
    with raises_on(cam, r"median depth is 829\.5 m.*depth_scale 0\.1 would put it at 0\.83 m"):
        bop.load_frame(dataset, 3, 0)
    edit_json(cam, lambda c: c["0"].update(depth_scale=0.0001))  # 1000 times too small
    with raises_on(cam, r"depth_scale 0\.1 would"):
        bop.load_frame(dataset, 3, 0)


def test_all_zero_depth(dataset):
    bop.save_frame(dataset, 3, 7, np.zeros((H, W)), K)
    with raises_on(scene(dataset) / "depth" / "000007.png", "no valid pixel"):
        bop.load_frame(dataset, 3, 7)


def test_unknown_objects_and_images(dataset):
    info = dataset / "models" / "models_info.json"
    with raises_on(info, r"unknown obj_id \[9\]"):
        bop.load_frame(dataset, 3, 0, object_ids=[1, 9])
    with raises_on(info, "unknown obj_id 9"):
        bop.load_models(dataset, [9])
    with raises_on(scene(dataset) / "scene_camera.json", "image 5 is not in scene 3"):
        bop.load_frame(dataset, 3, 5)


def test_models_in_metres_are_caught(dataset):
    ply = dataset / "models" / "obj_000001.ply"
    ply.write_bytes(trimesh.creation.box((0.05, 0.08, 0.12)).export(file_type="ply"))
    with raises_on(ply, "millimetres"):
        bop.load_models(dataset, [1])


# ---------------------------------------------------------------------------------------------------- plain frames


def write_plain(tmp_path: Path, intrinsics: dict, depth_mm: np.ndarray | None = None) -> tuple[Path, Path, Path]:
    depth_path = tmp_path / "depth.png"
    mm = scene_depth() * 1000 if depth_mm is None else depth_mm
    Image.fromarray(np.round(mm).astype(np.uint16)).save(depth_path)
    intr_path = tmp_path / "camera.json"
    intr_path.write_text(json.dumps(intrinsics))
    mesh_path = tmp_path / "mug.obj"
    trimesh.creation.cylinder(radius=40.0, height=90.0).export(mesh_path)  # millimetres
    return depth_path, intr_path, mesh_path


def test_plain_png_frame_with_mm_mesh(tmp_path):
    T = make_pose(np.eye(3), [0.0, 0.0, 0.5])
    intr = {"fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 23.5, "width": W, "height": H, "T_cam_world": T.tolist()}
    depth_path, intr_path, mesh_path = write_plain(tmp_path, intr)
    frame, models = load_plain_frame(depth_path, intr_path, [mesh_path, mesh_path])
    np.testing.assert_allclose(frame.depth, scene_depth(), atol=0.5e-3 + 1e-7)
    np.testing.assert_allclose(frame.camera.K, K)
    np.testing.assert_allclose(frame.camera.T_cam_world, T)
    assert frame.object_ids == [1, 1] and list(models) == [1]
    assert models[1].name == "mug" and models[1].mesh.extents[2] == pytest.approx(0.09)


def test_plain_npy_frame_nan_is_no_reading(tmp_path):
    depth = scene_depth()
    depth[0, 0] = np.nan
    np.save(tmp_path / "d.npy", depth)
    _, intr_path, mesh_path = write_plain(tmp_path, {"K": K.tolist()})
    frame, models = load_plain_frame(tmp_path / "d.npy", intr_path, [mesh_path], mesh_unit="mm")
    assert frame.depth[0, 0] == 0.0 and frame.depth[1, 1] == pytest.approx(depth[1, 1])
    assert frame.camera.T_cam_world is None and (frame.camera.width, frame.camera.height) == (W, H)


def test_plain_frame_errors(tmp_path):
    depth_path, intr_path, mesh_path = write_plain(tmp_path, {"K": K.tolist(), "width": 640, "height": 480})
    with raises_on(intr_path, "camera is 640x480 but the depth image is 64x48"):
        load_plain_frame(depth_path, intr_path, [mesh_path])
    intr_path.write_text(json.dumps({"fx": 60.0, "cx": 31.5, "cy": 23.5}))
    with raises_on(intr_path, "no intrinsics"):
        load_plain_frame(depth_path, intr_path, [mesh_path])
    intr_path.write_text(json.dumps({"K": K.tolist(), "depth_scale": 10.0}))
    with raises_on(depth_path, r"median depth is 8\.3 m.*depth_scale 1 in camera.json would put it at 0\.83 m"):
        load_plain_frame(depth_path, intr_path, [mesh_path])
    intr_path.write_text(json.dumps({"K": K.tolist()}))
    with raises_on(mesh_path, "90 m across"):
        load_plain_frame(depth_path, intr_path, [mesh_path], mesh_unit="m")
    with raises_on(tmp_path / "missing.ply", "not found"):
        load_plain_frame(depth_path, intr_path, [tmp_path / "missing.ply"])
    np.save(tmp_path / "mm.npy", scene_depth() * 1000)
    with raises_on(tmp_path / "mm.npy", r"multiplying the values by 0\.001"):
        load_plain_frame(tmp_path / "mm.npy", intr_path, [mesh_path])
