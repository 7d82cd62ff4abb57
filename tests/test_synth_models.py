"""Scenes of real shapes (``make-scenes --models`` with ycb_clutter, raised, leaning, tools), from small made-up BOP
models (boxes, a can, an open bowl, L- and U-shaped tools): valid BOP scenes whose listed objects rest where the
generator's physics holds them, distractors in the depth but not in scene_gt.json, a raised box under its objects."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from workbench.errors import InputError
from workbench.geometry import invert_pose, rotation_angle
from workbench.io import bop, readers
from workbench.physics.bullet import pybullet as pb
from workbench.synth import load_distractors, make_scenes, true_table_pose
from workbench.synth.config import SHAPE_CATEGORIES, SynthConfig
from workbench.synth.dataset import model_items
from workbench.synth.roles import BOX, OTHER, TOOL, VESSEL, role
from workbench.synth.sensor.model import axial_sigma
from workbench.synth.sequence import make_sequences
from workbench.synth.sim import Sim
from workbench.synth.views import pixel_rays, raycast

pytestmark = pytest.mark.slow  # the generator's pybullet world, V-HACD of the bowl (~10 s)

W, H = 160, 120


def _prism(xs, ys, cells, thickness: float) -> trimesh.Trimesh:
    """A closed flat shape of grid cells (i, j) between lines ``xs``, ``ys`` (m), ``thickness`` m high, centred:
    an L or U that stays closed when written and read back (boxes side by side would share faces)."""
    cells, faces, verts = set(cells), [], {}

    def v(x, y, z):
        return verts.setdefault((x, y, z), len(verts))
    for i, j in cells:
        x0, x1, y0, y1 = xs[i], xs[i + 1], ys[j], ys[j + 1]
        faces += [[v(x0, y0, 0), v(x1, y1, 0), v(x1, y0, 0)], [v(x0, y0, 0), v(x0, y1, 0), v(x1, y1, 0)]]
        faces += [[v(x0, y0, 1), v(x1, y0, 1), v(x1, y1, 1)], [v(x0, y0, 1), v(x1, y1, 1), v(x0, y1, 1)]]
        for (a, b), nb in ((((x0, y0), (x1, y0)), (i, j - 1)), (((x1, y0), (x1, y1)), (i + 1, j)),
                           (((x1, y1), (x0, y1)), (i, j + 1)), (((x0, y1), (x0, y0)), (i - 1, j))):
            if nb not in cells:  # an outer side
                faces += [[v(*a, 0), v(*b, 0), v(*b, 1)], [v(*a, 0), v(*b, 1), v(*a, 1)]]
    points = np.array(list(verts), dtype=np.float64) * [1.0, 1.0, thickness]
    mesh = trimesh.Trimesh(points, np.array(faces))
    return mesh.apply_translation(-mesh.bounds.mean(axis=0))


def _bowl() -> trimesh.Trimesh:
    """An open bowl 14 cm wide, 4 cm tall, its wall 6 mm thick: a revolved profile."""
    profile = np.array([[0, 0], [0.06, 0], [0.07, 0.04], [0.064, 0.04], [0.055, 0.006], [0, 0.006]])
    mesh = trimesh.creation.revolve(profile, sections=32)
    return mesh.apply_translation(-mesh.bounds.mean(axis=0))


MODELS = {
    1: trimesh.creation.box(extents=[0.06, 0.16, 0.21]),  # a cereal box: leans
    2: trimesh.creation.box(extents=[0.045, 0.09, 0.17]),
    3: trimesh.creation.box(extents=[0.11, 0.09, 0.035]),
    4: trimesh.creation.box(extents=[0.07, 0.05, 0.05]),
    5: trimesh.creation.cylinder(radius=0.033, height=0.1, sections=32),
    6: _bowl(),
    7: _prism([0, 0.02, 0.13], [0, 0.02, 0.09], [(0, 0), (1, 0), (0, 1)], 0.02),  # an L
    8: _prism([0, 0.02, 0.10, 0.12], [0, 0.02, 0.08], [(0, 0), (1, 0), (2, 0), (0, 1), (2, 1)], 0.02),  # a U
}
ROLES = {1: BOX, 2: BOX, 3: BOX, 4: BOX, 5: OTHER, 6: VESSEL, 7: TOOL, 8: TOOL}


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> Path:
    src = tmp_path_factory.mktemp("models")
    bop.save_models(src, MODELS)
    return src


@pytest.fixture(scope="module")
def dataset(models, tmp_path_factory) -> tuple[Path, list[dict]]:
    out = tmp_path_factory.mktemp("shapes")
    return out, make_scenes(out, list(SHAPE_CATEGORIES), 1, seed=0, width=W, height=H, models=models,
                            sensor="kinect-like")


def _distractor_entries(out: Path, scene_id: int) -> list[dict]:
    path = out / "test" / f"{scene_id:06d}" / "scene_distractors.json"
    return json.loads(path.read_text())["0"] if path.is_file() else []


def test_roles_of_the_models(models):
    assert {o.obj_id: role(o) for o in model_items(models)} == ROLES


def test_each_category_writes_a_valid_bop_scene(dataset):
    out, meta = dataset
    assert [m["category"] for m in meta] == list(SHAPE_CATEGORIES)
    loaded = bop.load_models(out)
    assert sorted(loaded) == sorted(MODELS)  # every given model is copied: distractors draw from them too
    for m in meta:
        frame = bop.load_frame(out, m["scene_id"], 0)
        assert frame.object_ids == m["obj_ids"] and frame.depth.shape == (H, W)
        assert len(set(m["obj_ids"])) == len(m["obj_ids"]) and min(m["visib_fract"]) >= 0.15, m
        rels = [r for r, _ in m["relations"]]
        n = len(m["obj_ids"])
        if m["category"] == "ycb_clutter":
            assert 6 <= n <= 8 and "touch" in rels, m
        elif m["category"] == "raised":
            assert 2 <= n <= 4 and m["table_pose"] is False and m["distractors"][0] == "support", m
        elif m["category"] == "leaning":
            assert 2 <= n <= 4 and rels[1] == "lean" and ROLES[m["obj_ids"][1]] == BOX, m
        else:
            assert 2 <= n <= 5 and ROLES[m["obj_ids"][0]] == TOOL, m


def _world_poses(out: Path, m: dict) -> np.ndarray:
    """The listed objects' written poses in the table frame. -> (K, 4, 4)"""
    frame = bop.load_frame(out, m["scene_id"], 0)
    return invert_pose(true_table_pose(out, m["scene_id"])) @ frame.gt_T_cam_obj


def _settled_poses(out: Path, m: dict, seconds: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """The listed objects' written poses (K, 4, 4, table frame) and where the generator's physics takes them in
    ``seconds``: a fresh world of the table (its size from scenes.json), the raised box if any, and the objects
    as their pieces."""
    T_world_cam = invert_pose(true_table_pose(out, m["scene_id"]))
    T = _world_poses(out, m)
    items = {o.obj_id: o for o in model_items(out)}
    sim = Sim(replace(SynthConfig(), table_size=tuple(m["table_size"])))
    try:
        sim.reset()
        for e, (mesh, T_cam) in zip(_distractor_entries(out, m["scene_id"]), load_distractors(out, m["scene_id"])):
            if e["kind"] == "support":
                sim.add_fixed_box(mesh.extents, T_world_cam @ T_cam)
        bodies = [sim.add_item(items[i], T_i, pieces=True) for i, T_i in zip(m["obj_ids"], T)]
        for _ in range(int(seconds / sim.cfg.dt)):
            pb.stepSimulation(physicsClientId=sim.cid)
        return T, np.array([sim.pose(b) for b in bodies])
    finally:
        sim.close()


def test_listed_objects_rest_where_physics_holds_them(dataset):
    out, meta = dataset
    for m in meta:
        T, after = _settled_poses(out, m)
        moved = np.linalg.norm(after[:, :3, 3] - T[:, :3, 3], axis=1)
        turned = np.degrees(rotation_angle(np.swapaxes(after[:, :3, :3], 1, 2) @ T[:, :3, :3]))
        assert np.all(moved < 5e-3) and np.all(turned < 2.0), (m, moved, turned)
        lowest = [trimesh.Trimesh(MODELS[i].vertices @ T_i[:3, :3].T + T_i[:3, 3], MODELS[i].faces).bounds[0, 2]
                  for i, T_i in zip(m["obj_ids"], T)]
        assert min(lowest) > -3e-3, (m, lowest)  # nothing sunk into the table


def test_distractors_are_in_the_depth_but_not_in_scene_gt(dataset):
    out, meta = dataset
    seen = set()
    for m in meta:
        entries = _distractor_entries(out, m["scene_id"])
        assert [e["kind"] for e in entries] == m.get("distractors", []), m
        gt = json.loads((out / "test" / f"{m['scene_id']:06d}" / "scene_gt.json").read_text())["0"]
        assert [g["obj_id"] for g in gt] == m["obj_ids"]
        assert not {e["obj_id"] for e in entries if e["kind"] == "model"} & set(m["obj_ids"])
        frame = bop.load_frame(out, m["scene_id"], 0)
        objects = [MODELS[i].copy().apply_transform(T) for i, T in zip(frame.object_ids, frame.gt_T_cam_obj)]
        posed = [mesh.copy().apply_transform(T) for mesh, T in load_distractors(out, m["scene_id"])]
        depth, idx = raycast(objects + posed, pixel_rays(frame.camera.K, W, H))
        for k, e in enumerate(entries):
            shown = (idx == len(objects) + k) & (frame.depth > 0)
            err = np.abs(frame.depth[shown] - depth[shown])
            if shown.sum() > 5:  # in view: the sensor saw it there (within 5 sigma of its noise, edges aside)
                assert np.mean(err < 5 * axial_sigma(depth[shown]) + 1e-3) > 0.8, (m, e["kind"])
                seen.add(e["kind"])
    assert "support" in seen and seen - {"support"}, seen


def test_raised_objects_rest_on_the_box_above_the_table(dataset):
    out, meta = dataset
    m = next(m for m in meta if m["category"] == "raised")
    scene_dir = out / "test" / f"{m['scene_id']:06d}"
    assert "cam_R_w2c" not in json.loads((scene_dir / "scene_camera.json").read_text())["0"]
    support = next(e for e in _distractor_entries(out, m["scene_id"]) if e["kind"] == "support")
    height = support["extents_mm"][2] * readers.MM
    assert 0.05 <= height <= 0.20 and min(support["extents_mm"][:2]) >= 300
    for i, T_i in zip(m["obj_ids"], _world_poses(out, m)):
        lowest = (MODELS[i].vertices @ T_i[:3, :3].T + T_i[:3, 3])[:, 2].min()
        assert lowest == pytest.approx(height, abs=3e-3), (m, i, lowest, height)


def test_the_support_found_is_the_raised_box_where_the_objects_stand_on_it_and_the_table_elsewhere(dataset):
    from workbench.problem.build import load_bop_problem

    out, meta = dataset
    for m in meta:  # at 160x120: a coarse depth, as a far sensor's
        frame, problem = load_bop_problem(out, m["scene_id"], 0)
        poses = invert_pose(problem.camera.T_cam_world)[None] @ frame.gt_T_cam_obj
        lowest = [(MODELS[i].vertices @ T[:3, :3].T + T[:3, 3])[:, 2].min() for i, T in zip(m["obj_ids"], poses)]
        # every object rests on the support found (z = 0 of the problem's table frame), within the plane's noise
        assert np.min(lowest) == pytest.approx(0.0, abs=0.01), (m["category"], lowest)


def test_a_sequences_carried_support_is_kept_and_a_given_table_pose_raised_only_when_asked(dataset):
    """A tracked frame carries the support the frame before found (``raised=False``): kept as it is, raised box
    and all. The table pose itself, given with ``raised=False``, stays the table; looked at (the default), the objects
    stand on the raised box above it."""
    from workbench.problem.build import load_bop_problem
    from workbench.problem.support import estimate_support

    out, meta = dataset
    raised = [m for m in meta if m["category"] == "raised"]
    assert raised
    for m in raised:
        frame, problem = load_bop_problem(out, m["scene_id"], 0)
        found = problem.camera.T_cam_world
        carried, _ = estimate_support(replace(frame, camera=frame.camera.with_pose(found)), raised=False)
        assert np.array_equal(carried.T_cam_world, found)
        table = replace(frame, camera=frame.camera.with_pose(true_table_pose(out, m["scene_id"])))
        kept, _ = estimate_support(table, raised=False)
        looked, _ = estimate_support(table)
        assert np.array_equal(kept.T_cam_world, table.camera.T_cam_world)
        above_table, above_box = (invert_pose(c.T_cam_world)[2, 3] for c in (table.camera, looked))
        assert above_table - above_box > 0.02  # the camera's height over the box is less by the box's


def test_shape_categories_need_fitting_models(models, tmp_path):
    with pytest.raises(InputError, match="--models"):
        make_scenes(tmp_path / "a", ["raised"], 1, seed=0, width=W, height=H)
    with pytest.raises(InputError, match="sequences do not take"):
        make_sequences(tmp_path / "s", ["tools"], 1, 2, seed=0, width=W, height=H)
    round_only = tmp_path / "round"
    bop.save_models(round_only, {5: MODELS[5], 9: trimesh.creation.icosphere(radius=0.04)})
    with pytest.raises(InputError, match="leaning needs a box"):
        make_scenes(tmp_path / "b", ["leaning"], 1, seed=0, width=W, height=H, models=round_only)
    with pytest.raises(InputError, match="tools needs a tool"):
        make_scenes(tmp_path / "c", ["tools"], 1, seed=0, width=W, height=H, models=round_only)
