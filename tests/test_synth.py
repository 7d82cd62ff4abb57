"""Synthetic scenes: categories hold when read back from disk, the sensor model's statistics, the demo; the
real-like desks: distractors, frames without the table pose, the generated can and mug."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from workbench.errors import InputError
from workbench.geometry import invert_pose, make_pose, rot_z
from workbench.io import bop
from workbench.io.results import read_results_csv
from workbench.problem.support import estimate_support
from workbench.score import metrics
from workbench.synth import CATEGORIES, load_distractors, make_demo, make_scenes, true_table_pose, visible_masks
from workbench.synth.config import DESKS, PAPER_CATEGORIES, SHAPE_CATEGORIES, SynthConfig
from workbench.synth.objects import BOX_BY_ID, BOXES, OBJECT_BY_ID, OBJECTS, ROUND, item_mesh, tilt_deg
from workbench.synth.scenes import generate_scene
from workbench.synth.sensor.model import SensorModel, apply_sensor, axial_sigma
from workbench.synth.sim import Sim, contact_distances, item_distances
from workbench.synth.views import pixel_rays, raycast

pytestmark = pytest.mark.slow  # needs the generator's pybullet world

W, H = 320, 240
TOUCH = 1e-3  # m: boxes closer than this touch
BUILT_IN = [c for c in CATEGORIES if c not in SHAPE_CATEGORIES]  # real shapes need given models: test_synth_models


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> tuple[Path, list[dict]]:
    out = tmp_path_factory.mktemp("synth")
    return out, make_scenes(out, BUILT_IN, 1, seed=0, width=W, height=H, sensor="kinect-like")


def _world(frame, dataset=None) -> np.ndarray:
    """Ground-truth T_world_obj (K, 4, 4); the table pose from scene_table.json where the frame omits it."""
    T_cam_world = frame.camera.T_cam_world
    if T_cam_world is None:
        T_cam_world = true_table_pose(dataset, frame.scene_id, frame.im_id)
    return invert_pose(T_cam_world) @ frame.gt_T_cam_obj


def test_every_category_written_once_with_its_relations(dataset):
    out, meta = dataset
    assert [m["category"] for m in meta] == BUILT_IN
    expected = {"touching": {"touch"}, "stacked": {"stack"}, "slant": {"slant"}, "occluded": {"hide"}}
    sizes = {"three": 3, "four": 4}
    for m in meta:
        rels = [r for r, _ in m["relations"][1:]]
        kinds = [OBJECT_BY_ID[i].kind for i in m["obj_ids"]]
        if m["category"] in expected:
            assert set(rels) == expected[m["category"]] and len(m["obj_ids"]) == 2
        elif m["category"] in sizes:
            assert len(m["obj_ids"]) == sizes[m["category"]] and len(set(rels)) >= 2
        elif m["category"] == "clutter":
            assert 4 <= len(m["obj_ids"]) <= 6 and {"touch", "stack"} <= set(rels) <= {"touch", "stack", "free"}
            assert "box" in kinds and set(kinds) - {"box"} and 2 <= len(m["distractors"]) <= 4, m
        elif m["category"] in ("handle_hidden", "handle_shown"):  # the mug first, boxes standing free
            assert kinds[0] == "mug" and set(kinds[1:]) <= {"box"} and set(rels) <= {"free"} and len(kinds) <= 3
        elif m["category"] == "lying":
            assert 2 <= len(m["obj_ids"]) <= 4 and {r for r, _ in m["relations"]} == {"lie"}, m
        else:  # mixed
            assert 2 <= len(m["obj_ids"]) <= 3 and "box" in kinds and set(kinds) - {"box"}, m
            assert 1 <= len(m["distractors"]) <= 3 and m["table_pose"] is False, m
        if m["category"] not in DESKS:  # the paper's desk: the table pose given, no distractors
            assert "distractors" not in m and "table_pose" not in m
        if m["category"] in PAPER_CATEGORIES:
            assert set(kinds) == {"box"} and "distractors" not in m and "table_pose" not in m
        assert len(set(m["obj_ids"])) == len(m["obj_ids"])


def test_relations_hold_in_the_reloaded_poses(dataset):
    out, meta = dataset
    for m in meta:
        frame = bop.load_frame(out, m["scene_id"], 0)
        assert frame.object_ids == m["obj_ids"] and frame.depth.shape == (H, W)
        T = _world(frame, out)
        d = item_distances([OBJECT_BY_ID[i] for i in frame.object_ids], T)
        table = len(T)
        for child, (rel, parent) in enumerate(m["relations"]):
            tilt = tilt_deg(T[child, :3, :3])
            if rel == "lie":  # on the table in any pose
                assert d[child, table] < TOUCH, (m, d)
                continue
            if rel in ("base", "free"):
                assert d[child, table] < TOUCH and tilt < 3, m
                if rel == "free":  # clear of every other object
                    assert np.all(np.delete(d[child, :table], child) > TOUCH), (m, d)
                continue
            assert d[child, parent] < TOUCH, (m, rel, d)
            if rel in ("touch", "hide"):
                assert d[child, table] < TOUCH and tilt < 3, (m, rel)
            elif rel == "stack":  # on the other box, clear of the table
                assert d[child, table] > 5e-3, (m, d)
            elif rel == "slant":
                assert d[child, table] < TOUCH and 10 <= tilt <= 80, (m, tilt)


def test_visibility_info_matches_masks_and_hides_the_occluded_box(dataset):
    out, meta = dataset
    for m in meta:
        scene_dir = out / "test" / f"{m['scene_id']:06d}"
        info = json.loads((scene_dir / "scene_gt_info.json").read_text())["0"]
        frame = bop.load_frame(out, m["scene_id"], 0)
        meshes = [item_mesh(OBJECT_BY_ID[i]) for i in frame.object_ids]
        distractors = load_distractors(out, m["scene_id"])  # they hide objects too
        poses = np.concatenate([frame.gt_T_cam_obj, np.array([T for _, T in distractors]).reshape(-1, 4, 4)])
        recomputed = visible_masks(frame.camera.K, W, H, meshes + [mesh for mesh, _ in distractors], poses)
        for k, entry in enumerate(info):
            png = np.asarray(Image.open(scene_dir / "mask_visib" / f"000000_{k:06d}.png")) > 0
            assert png.sum() == entry["px_count_visib"]
            assert entry["visib_fract"] == pytest.approx(entry["px_count_visib"] / entry["px_count_all"])
            # Ray-cast again from the reloaded poses without the table: the same pixels (the table hides nothing).
            assert abs(int(recomputed[k].sum()) - entry["px_count_visib"]) <= 0.02 * entry["px_count_all"] + 2
            hidden = m["relations"][k][0] == "hide"
            assert (entry["visib_fract"] < 0.1) if hidden else (entry["visib_fract"] >= 0.15), (m, k, entry)
    occluded = next(m for m in meta if m["category"] == "occluded")
    assert occluded["visib_fract"][1] < 0.1 and occluded["visib_fract"][0] > 0.5


def test_models_carry_box_symmetries(dataset):
    out, _ = dataset
    models = bop.load_models(out)
    assert sorted(models) == [o.obj_id for o in OBJECTS]
    for b in BOXES:
        assert np.allclose(sorted(models[b.obj_id].mesh.extents), sorted(b.extents), atol=1e-6)
    assert len(models[1].symmetries) == 4  # cracker box: three different sides
    assert len(models[5].symmetries) == 8  # wood block: square section


def test_scene_noise_matches_the_sensor_model():
    cfg = SynthConfig(width=W, height=H)
    sim = Sim(cfg)
    try:
        sample = generate_scene(sim, "touching", np.random.default_rng(3), cfg)
    finally:
        sim.close()
    both = (sample.depth > 0) & (sample.clean_depth > 0)
    z = sample.clean_depth[both].astype(np.float64)
    r = sample.depth[both] - z
    total = np.sqrt(axial_sigma(z) ** 2 + cfg.sensor.quantum**2 / 12)
    assert 0.7 < np.std(r / total) < 1.3
    on_boxes = both & np.any(sample.mask_visib, axis=0)
    assert 0.7 < np.std(r[on_boxes[both]] / total[on_boxes[both]]) < 1.3
    missing = 1 - both.sum() / (sample.clean_depth > 0).sum()
    assert 0.015 < missing < 0.15


def test_sensor_noise_at_known_depth_and_dropouts():
    rng = np.random.default_rng(0)
    model = SensorModel()
    clean = np.full((200, 300), 1.2, dtype=np.float32)
    clean[:, 150:] = 0.8  # a 40 cm step: a discontinuity down the middle
    noisy = apply_sensor(clean, rng, model)
    for z, cols in ((1.2, slice(0, 140)), (0.8, slice(160, 300))):
        vals = noisy[:, cols][noisy[:, cols] > 0]
        expected = np.sqrt(axial_sigma(z, model) ** 2 + model.quantum**2 / 12)
        assert abs(np.std(vals - z) / expected - 1) < 0.3
        assert abs(np.mean(vals) - z) < 3e-4
    assert np.allclose(noisy / model.quantum, np.round(noisy / model.quantum), atol=1e-3)
    far = noisy[:, :140]
    assert 0.01 < np.mean(far == 0) < 0.03  # random dropouts only
    assert np.mean(noisy[:, 149:151] == 0) > 0.6  # the step loses most readings


def test_same_seed_same_scene_and_unknown_category(tmp_path):
    a = make_scenes(tmp_path / "a", ["slant"], 1, seed=5, width=160, height=120, sensor="kinect-like")
    b = make_scenes(tmp_path / "b", ["slant"], 1, seed=5, width=160, height=120, sensor="kinect-like")
    fa, fb = bop.load_frame(tmp_path / "a", 0, 0), bop.load_frame(tmp_path / "b", 0, 0)
    assert a == b and np.allclose(fa.gt_T_cam_obj, fb.gt_T_cam_obj) and np.array_equal(fa.depth, fb.depth)
    with pytest.raises(InputError, match="unknown"):
        make_scenes(tmp_path / "c", ["piled"], 1, seed=0)


def test_demo_is_small_and_two_touching_boxes(tmp_path):
    meta = make_demo(tmp_path)
    size = sum(p.stat().st_size for p in tmp_path.rglob("*") if p.is_file())
    assert size < 1_000_000
    frame = bop.load_frame(tmp_path, 0, 0)
    assert frame.depth.shape == (480, 640) and len(frame.object_ids) == 2 == len(meta[0]["obj_ids"])
    ext = np.array([BOX_BY_ID[i].extents for i in frame.object_ids])
    d = contact_distances(ext, _world(frame))
    assert d[0, 1] < TOUCH and d[1, 0] < TOUCH


# ------------------------------------------------------------------------------------------------------------------
# Real-like desks


def _scene_dirs(out: Path, meta: list[dict], categories) -> list[tuple[dict, Path]]:
    return [(m, out / "test" / f"{m['scene_id']:06d}") for m in meta if m["category"] in categories]


def test_distractors_are_in_the_depth_but_not_in_scene_gt(dataset):
    out, meta = dataset
    for m, scene_dir in _scene_dirs(out, meta, ("clutter", "mixed")):
        gt = json.loads((scene_dir / "scene_gt.json").read_text())["0"]
        assert [g["obj_id"] for g in gt] == m["obj_ids"]  # the objects of interest, and nothing else
        entries = json.loads((scene_dir / "scene_distractors.json").read_text())["0"]
        assert [e["kind"] for e in entries] == m["distractors"]
        frame = bop.load_frame(out, m["scene_id"], 0)
        K = frame.camera.K
        distractors = load_distractors(out, m["scene_id"])
        objects = [item_mesh(OBJECT_BY_ID[i]).apply_transform(T)
                   for i, T in zip(frame.object_ids, frame.gt_T_cam_obj)]
        posed = [mesh.copy().apply_transform(T) for mesh, T in distractors]
        depth, idx = raycast(objects + posed, pixel_rays(K, W, H))
        shown = (idx >= len(objects)) & (frame.depth > 0)  # pixels where a distractor is the nearest thing
        assert shown.sum() > 30, m  # unexplained by the objects the estimator is told about
        # The sensor saw the distractor there: within 5 sigma of the noise (holes and edges aside).
        err = np.abs(frame.depth[shown] - depth[shown])
        assert np.mean(err < 5 * axial_sigma(depth[shown]) + 1e-3) > 0.9, (m, np.median(err))
        # ... and no distractor touches an object: they were placed clear of every relation.
        world = invert_pose(true_table_pose(out, m["scene_id"]))
        for mesh, T in distractors:
            lowest = (mesh.copy().apply_transform(world @ T)).bounds[0, 2]
            assert abs(lowest) < 1e-6  # resting on the table


def test_frames_without_the_table_pose_load_and_the_table_is_found(dataset):
    out, meta = dataset
    omitted = [(m, d) for m, d in _scene_dirs(out, meta, CATEGORIES) if not m.get("table_pose", True)]
    assert omitted and all(m["category"] in ("clutter", "mixed") for m, _ in omitted)
    for m, scene_dir in omitted:
        cam = json.loads((scene_dir / "scene_camera.json").read_text())["0"]
        assert "cam_R_w2c" not in cam and "cam_t_w2c" not in cam
        frame = bop.load_frame(out, m["scene_id"], 0)
        assert frame.camera.T_cam_world is None
        camera, _ = estimate_support(frame)
        T_true = true_table_pose(out, m["scene_id"])
        n_est, n_true = camera.T_cam_world[:3, 2], T_true[:3, 2]  # the table normal in the camera frame
        assert np.degrees(np.arccos(np.clip(n_est @ n_true, -1, 1))) < 1.0, m
        # The estimated plane passes within 5 mm of the true table origin (both in the camera frame).
        assert abs(n_est @ (T_true[:3, 3] - camera.T_cam_world[:3, 3])) < 0.005, m


def test_can_and_mug_models_are_watertight_with_their_dimensions(dataset):
    out, _ = dataset
    models = bop.load_models(out)
    can, mug = ROUND
    for item in (can, mug):
        mesh = models[item.obj_id].mesh
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
        assert np.allclose(mesh.extents, item.extents, atol=1e-4), (item, mesh.extents)
        assert np.allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-4)  # centred on its bounding box
    assert models[can.obj_id].mesh.volume == pytest.approx(np.pi * can.radius**2 * can.height, rel=0.01)
    s = mug.shape
    body = np.pi * (s.radius**2 * s.height - (s.radius - s.wall) ** 2 * (s.height - s.bottom))  # hollow
    width = 2 * s.radius * np.sin(np.pi * s.handle_segments / 64)  # the handle spans that many of 64 wall segments
    handle = np.pi * (s.handle_reach + s.handle_span / 2) / 2 * s.handle_thickness * width  # ~half an ellipse
    assert models[mug.obj_id].mesh.volume == pytest.approx(body + handle, rel=0.03)
    # The mug is hollow: looking down its axis from 10 cm above the rim, one sees its inner bottom.
    axis_x = -(s.handle_reach + s.handle_thickness / 2) / 2  # the body's axis in the centred model frame
    down = np.array([[axis_x, 0.0, s.height / 2 + 0.1, 0.0, 0.0, -1.0]], dtype=np.float32)
    hit, _ = raycast([models[mug.obj_id].mesh], down)
    assert hit[0] == pytest.approx(0.1 + s.height - s.bottom, abs=1e-5)
    # The can looks the same turned about its axis (BOP symmetries_continuous), the mug does not.
    info = json.loads((out / "models" / "models_info.json").read_text())
    assert info[str(can.obj_id)]["symmetries_continuous"] == [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}]
    assert "symmetries_continuous" not in info[str(mug.obj_id)]
    turned = make_pose(rot_z(np.radians(37.0)), np.zeros(3))
    assert metrics.rotation_error(np.eye(4), turned, models[can.obj_id].symmetries) < 5.01
    assert metrics.rotation_error(np.eye(4), turned, models[mug.obj_id].symmetries) == pytest.approx(37.0)


def _handle_pixels(frame, mask_visib: np.ndarray) -> int:
    """The mug's (object 0's) visible pixels that a handle-less body in its place would not cover: ray-cast here
    against a closed cylinder of the mug's body, independently of the generator's own count."""
    s = ROUND[1].shape
    body = trimesh.creation.cylinder(radius=s.radius, height=s.height, sections=64)
    axis_x = -(s.handle_reach + s.handle_thickness / 2) / 2  # the body's axis in the centred model frame
    body.apply_transform(frame.gt_T_cam_obj[0] @ make_pose(np.eye(3), [axis_x, 0.0, 0.0]))
    _, idx = raycast([body], pixel_rays(frame.camera.K, W, H))
    return int(np.count_nonzero(mask_visib & (idx != 0)))


def test_handle_categories_hide_the_mugs_handle_behind_its_body_or_show_it(dataset):
    out, meta = dataset
    for category in ("handle_hidden", "handle_shown"):
        m = next(m for m in meta if m["category"] == category)
        frame = bop.load_frame(out, m["scene_id"], 0)
        mask = np.asarray(Image.open(out / "test" / f"{m['scene_id']:06d}" / "mask_visib" / "000000_000000.png")) > 0
        T = frame.gt_T_cam_obj[0]
        away = T[:3, 3] / np.linalg.norm(T[:3, 3])  # from the camera to the mug
        handle = T[:3, 0]  # the handle sticks out along the mug's +x
        n = _handle_pixels(frame, mask)
        if category == "handle_hidden":
            assert n <= 6 and handle @ away > 0.5, (n, handle @ away)  # it points away, behind the body
        else:
            assert n >= 10, n


def test_lying_scenes_draw_from_given_models_and_copy_them(tmp_path):
    """--models: scenes of any BOP models, here two made-up ones (a long box and a can), in their stable poses,
    written with the source's models and symmetries."""
    src = tmp_path / "src"
    flip = make_pose(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
    bop.save_models(src, {3: trimesh.creation.box(extents=[0.04, 0.06, 0.2]),
                          9: trimesh.creation.cylinder(radius=0.03, height=0.1, sections=32)}, {9: flip[None]})
    meta = make_scenes(tmp_path / "out", ["lying"], 2, seed=0, width=W, height=H, models=src, sensor="kinect-like")
    assert all(set(m["obj_ids"]) <= {3, 9} and m["category"] == "lying" for m in meta)
    copied, given = tmp_path / "out" / "models", src / "models"
    assert (copied / "obj_000003.ply").read_bytes() == (given / "obj_000003.ply").read_bytes()
    assert json.loads((copied / "models_info.json").read_text()) == json.loads((given / "models_info.json").read_text())
    for m in meta:
        frame = bop.load_frame(tmp_path / "out", m["scene_id"], 0)
        T = _world(frame)
        for obj_id, T_obj in zip(frame.object_ids, T):  # resting on the table: its lowest point on it
            lowest = (trimesh.creation.box(extents=[0.04, 0.06, 0.2]) if obj_id == 3 else
                      trimesh.creation.cylinder(radius=0.03, height=0.1, sections=32)).apply_transform(T_obj)
            assert abs(lowest.bounds[0, 2]) < 2e-3, (m, lowest.bounds)
    with pytest.raises(InputError, match="with --models"):
        make_scenes(tmp_path / "bad", ["touching"], 1, seed=0, models=src)


def test_desk_options_override_the_category(tmp_path):
    meta = make_scenes(tmp_path, ["touching"], 1, seed=0, width=W, height=H, distractors=2, table_pose=0.0,
                       sensor="kinect-like")
    scene_dir = tmp_path / "test" / "000000"
    assert meta[0]["table_pose"] is False and len(meta[0]["distractors"]) == 2
    assert "cam_R_w2c" not in json.loads((scene_dir / "scene_camera.json").read_text())["0"]
    assert len(load_distractors(tmp_path, 0)) == 2
    with pytest.raises(InputError, match="distractors"):
        make_scenes(tmp_path / "b", ["touching"], 1, seed=0, distractors=-1)
    with pytest.raises(InputError, match="table pose"):
        make_scenes(tmp_path / "c", ["touching"], 1, seed=0, table_pose=1.5)


def test_estimate_runs_on_a_frame_without_the_table_pose(dataset, tmp_path):
    from workbench.cli import main

    out, meta = dataset
    m = next(m for m in meta if m["category"] == "mixed")
    csv = tmp_path / "r.csv"
    assert main(["estimate", str(out), "--scene", str(m["scene_id"]), "--frame", "0", "--particles", "16",
                 "--iterations", "2", "--out", str(csv)]) == 0
    rows = read_results_csv(csv)
    assert sorted({r.obj_id for r in rows}) == sorted(m["obj_ids"])  # each object's modes, one row or more
    assert all(np.all(np.isfinite(r.T_cam_obj)) and 0.2 < r.T_cam_obj[2, 3] < 3.0 for r in rows)
