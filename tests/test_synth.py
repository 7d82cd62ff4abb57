"""Synthetic scenes: categories hold when read back from disk, the sensor model's statistics, the demo."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from workbench import bop, synth
from workbench.errors import InputError
from workbench.geometry import invert_pose
from workbench.sensor import SensorModel, apply_sensor, axial_sigma

W, H = 320, 240
TOUCH = 1e-3  # m: boxes closer than this touch


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> tuple[Path, list[dict]]:
    out = tmp_path_factory.mktemp("synth")
    return out, synth.make_scenes(out, list(synth.CATEGORIES), 1, seed=0, width=W, height=H)


def _world(frame) -> np.ndarray:
    return invert_pose(frame.camera.T_cam_world) @ frame.gt_T_cam_obj


def test_every_category_written_once_with_its_relations(dataset):
    out, meta = dataset
    assert [m["category"] for m in meta] == list(synth.CATEGORIES)
    expected = {"touching": {"touch"}, "stacked": {"stack"}, "slant": {"slant"}, "occluded": {"hide"}}
    sizes = {"three": 3, "four": 4}
    for m in meta:
        rels = [r for r, _ in m["relations"][1:]]
        if m["category"] in expected:
            assert set(rels) == expected[m["category"]] and len(m["obj_ids"]) == 2
        else:
            assert len(m["obj_ids"]) == sizes[m["category"]] and len(set(rels)) >= 2


def test_relations_hold_in_the_reloaded_poses(dataset):
    out, meta = dataset
    for m in meta:
        frame = bop.load_frame(out, m["scene_id"], 0)
        assert frame.object_ids == m["obj_ids"] and frame.depth.shape == (H, W)
        T = _world(frame)
        ext = np.array([synth.BOX_BY_ID[i].extents for i in frame.object_ids])
        d = synth.contact_distances(ext, T)
        table = len(T)
        for child, (rel, parent) in enumerate(m["relations"]):
            tilt = synth.tilt_deg(T[child, :3, :3])
            if rel == "base":
                assert d[child, table] < TOUCH and tilt < 3, m
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
        meshes = [synth.box_mesh(synth.BOX_BY_ID[i].extents) for i in frame.object_ids]
        recomputed = synth.visible_masks(frame.camera.K, W, H, meshes, frame.gt_T_cam_obj)
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
    assert sorted(models) == [b.obj_id for b in synth.BOXES]
    for b in synth.BOXES:
        assert np.allclose(sorted(models[b.obj_id].mesh.extents), sorted(b.extents), atol=1e-6)
    assert len(models[1].symmetries) == 4  # cracker box: three different sides
    assert len(models[5].symmetries) == 8  # wood block: square section


def test_scene_noise_matches_the_sensor_model():
    cfg = synth.SynthConfig(width=W, height=H)
    sim = synth.Sim(cfg)
    try:
        sample = synth.generate_scene(sim, "touching", np.random.default_rng(3), cfg)
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
    a = synth.make_scenes(tmp_path / "a", ["slant"], 1, seed=5, width=160, height=120)
    b = synth.make_scenes(tmp_path / "b", ["slant"], 1, seed=5, width=160, height=120)
    fa, fb = bop.load_frame(tmp_path / "a", 0, 0), bop.load_frame(tmp_path / "b", 0, 0)
    assert a == b and np.allclose(fa.gt_T_cam_obj, fb.gt_T_cam_obj) and np.array_equal(fa.depth, fb.depth)
    with pytest.raises(InputError, match="unknown"):
        synth.make_scenes(tmp_path / "c", ["piled"], 1, seed=0)


def test_demo_is_small_and_two_touching_boxes(tmp_path):
    meta = synth.make_demo(tmp_path)
    size = sum(p.stat().st_size for p in tmp_path.rglob("*") if p.is_file())
    assert size < 1_000_000
    frame = bop.load_frame(tmp_path, 0, 0)
    assert frame.depth.shape == (480, 640) and len(frame.object_ids) == 2 == len(meta[0]["obj_ids"])
    ext = np.array([synth.BOX_BY_ID[i].extents for i in frame.object_ids])
    d = synth.contact_distances(ext, _world(frame))
    assert d[0, 1] < TOUCH and d[1, 0] < TOUCH
