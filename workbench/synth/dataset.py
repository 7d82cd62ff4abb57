"""Generated scenes as a BOP dataset: ``make_scenes`` and ``make_demo`` write the frames, their masks and the
object models, and what BOP has no field for (distractors, a table pose left out) in files of their own, read back
by ``load_distractors`` and ``true_table_pose``."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from workbench.errors import InputError
from workbench.geometry import make_pose
from workbench.io import bop, readers
from workbench.score.metrics import box_symmetries
from workbench.synth.config import CATEGORIES, DESKS, MODEL_CATEGORIES, SHAPE_CATEGORIES, DeskSpec, SynthConfig
from workbench.synth.distractors import Distractor, distractor_mesh
from workbench.synth.objects import BOXES, ROUND, MeshItem, box_mesh, item_mesh
from workbench.synth.scenes import SceneSample, generate_scene
from workbench.synth.sensor.model import DEFAULT_SENSOR, SensorName, check_sensor, sensor_model
from workbench.synth.shape_layouts import check_models
from workbench.synth.sim import Sim


def _write_masks(folder: Path, im_id: int, masks: np.ndarray) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for k, m in enumerate(masks):
        Image.fromarray((m * 255).astype(np.uint8)).save(folder / f"{im_id:06d}_{k:06d}.png")


def write_scene(out: Path, scene_id: int, sample: SceneSample, cfg: SynthConfig, split: str = "test") -> None:
    """The sample as BOP frame ``im_id`` 0 of ``scene_id``, with mask and mask_visib PNGs.

    Only the objects of interest go into scene_gt.json (the estimator reads from it which objects are present).
    Distractors, if any, are listed in scene_distractors.json; a table pose left out of scene_camera.json is
    kept in scene_table.json, both for reference and scoring (:func:`load_distractors`, :func:`true_table_pose`).
    """
    gt = [(p.item.obj_id, sample.T_cam_world @ p.T) for p in sample.layout]
    T_given = sample.T_cam_world if sample.table_pose else None
    bop.save_frame(out, scene_id, 0, sample.depth, cfg.K(), T_given, gt, sample.gt_info(), split=split)
    scene_dir = Path(out) / split / f"{scene_id:06d}"
    _write_masks(scene_dir / "mask_visib", 0, sample.mask_visib)
    _write_masks(scene_dir / "mask", 0, sample.mask_all)
    if not sample.table_pose:
        R, t = sample.T_cam_world[:3, :3], sample.T_cam_world[:3, 3] / readers.MM
        table = {"cam_R_w2c": R.ravel().tolist(), "cam_t_w2c": t.tolist(),
                 "table_size": [v / readers.MM for v in sample.table_size]}
        _write_json(scene_dir / "scene_table.json", {"0": table})
    if sample.distractors:
        _write_json(scene_dir / "scene_distractors.json",
                    {"0": [_distractor_entry(d, sample.T_cam_world) for d in sample.distractors]})


def _distractor_entry(d: Distractor, T_cam_world: np.ndarray) -> dict:
    """A distractor as JSON: kind, sizes in mm (a model: its obj_id), pose in the camera frame (BOP's cam_R_m2c,
    cam_t_m2c)."""
    T = T_cam_world @ d.T
    params = {k: (np.asarray(v) / readers.MM).tolist() for k, v in d.params.items()}
    model = {} if d.item is None else {"obj_id": d.item.obj_id}
    return {"kind": d.kind, **model, **{f"{k}_mm": v for k, v in params.items()},
            "cam_R_m2c": T[:3, :3].ravel().tolist(), "cam_t_m2c": (T[:3, 3] / readers.MM).tolist()}


def load_distractors(dataset: Path, scene_id: int, im_id: int = 0,
                     split: str = "test") -> list[tuple[trimesh.Trimesh, np.ndarray]]:
    """The distractors of a generated frame, a raised box included: (model mesh in metres, T_cam_obj (4, 4)
    metres) each; [] if none. A model distractor's mesh is the dataset's model of its obj_id."""
    path = Path(dataset) / split / f"{scene_id:06d}" / "scene_distractors.json"
    if not path.is_file():
        return []
    out = []
    for e in readers.read_json(path).get(str(im_id), []):
        params = {k[:-3]: np.asarray(v) * readers.MM for k, v in e.items() if k.endswith("_mm")}
        T = readers.parse_pose(e["cam_R_m2c"], e["cam_t_m2c"], path, f"image {im_id} distractor")
        if e["kind"] == "model":
            mesh = bop.load_models(dataset, [e["obj_id"]])[e["obj_id"]].mesh
        else:
            mesh = distractor_mesh(e["kind"], params)
        out.append((mesh, T))
    return out


def true_table_pose(dataset: Path, scene_id: int, im_id: int = 0, split: str = "test") -> np.ndarray:
    """T_cam_world (4, 4, metres) of a generated frame: from scene_camera.json, else from scene_table.json."""
    return _table_pose_in(Path(dataset) / split / f"{scene_id:06d}", im_id)


def frame_table_pose(frame) -> np.ndarray:
    """The true T_cam_world (4, 4) of a loaded generated ``Frame``: its camera's, else its scene's
    scene_table.json (found next to its depth image), for scoring frames that do not give it."""
    if frame.camera.T_cam_world is not None:
        return frame.camera.T_cam_world
    return _table_pose_in(Path(frame.source).parent.parent, frame.im_id)


def _table_pose_in(scene_dir: Path, im_id: int) -> np.ndarray:
    for name in ("scene_camera.json", "scene_table.json"):
        path = scene_dir / name
        entry = readers.read_json(path).get(str(im_id), {}) if path.is_file() else {}
        if "cam_R_w2c" in entry:
            return readers.parse_pose(entry["cam_R_w2c"], entry["cam_t_w2c"], path, f"image {im_id} table pose")
    raise InputError(scene_dir, f"image {im_id}: no table pose in scene_camera.json or scene_table.json")


def save_box_models(out: Path, obj_ids: list[int] | None = None) -> None:
    """The boxes' meshes and symmetries as BOP models."""
    boxes = [b for b in BOXES if obj_ids is None or b.obj_id in obj_ids]
    bop.save_models(
        out, {b.obj_id: box_mesh(b.extents) for b in boxes}, {b.obj_id: box_symmetries(b.extents) for b in boxes}
    )


def save_object_models(out: Path) -> None:
    """Every object's mesh as a BOP model: the boxes with their discrete symmetries, the can with its continuous
    one about z (and the flip end over end), the mug with none (its handle breaks every symmetry)."""
    save_box_models(out)
    can, mug = ROUND
    flip = make_pose(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
    bop.save_models(out, {can.obj_id: item_mesh(can), mug.obj_id: item_mesh(mug)}, {can.obj_id: flip[None]},
                    symmetries_continuous={can.obj_id: [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]})


def _name_models(out: Path, names: dict[int, str]) -> None:
    """Give the models ``names`` in models_info.json (the ``name`` the workbench reads): the demo's objects are
    called "foam_brick", not "obj_000006"."""
    path = Path(out) / "models" / "models_info.json"
    info = readers.read_json(path)
    for obj_id, name in names.items():
        info[str(obj_id)] = {"name": name, **info[str(obj_id)]}
    _write_json(path, info)


def _write_camera_json(out: Path, cfg: SynthConfig) -> None:
    K = cfg.K()
    cam = {"cx": K[0, 2], "cy": K[1, 2], "fx": K[0, 0], "fy": K[1, 1], "width": cfg.width, "height": cfg.height,
           "depth_scale": 0.1}
    _write_json(Path(out) / "camera.json", cam)


def _write_json(path: Path, content: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(content, indent=2) + "\n")


def _scene_meta(scene_id: int, sample: SceneSample) -> dict:
    meta = {
        "scene_id": scene_id,
        "category": sample.category,
        "obj_ids": [p.item.obj_id for p in sample.layout],
        "relations": [[p.relation, p.parent] for p in sample.layout],
        "visib_fract": [round(float(v), 4) for v in sample.visib_fract],
        "tries": sample.tries,
    }
    # Only where a scene differs from the paper's set-up (absent: 1.2 x 0.8 m table, pose given, no distractors).
    if sample.table_size != SynthConfig.table_size:
        meta["table_size"] = [round(v, 4) for v in sample.table_size]
    if not sample.table_pose:
        meta["table_pose"] = False
    if sample.distractors:
        meta["distractors"] = [d.kind for d in sample.distractors]
    return meta


def check_out_folder(out: Path, force: bool) -> None:
    """A dataset is written into a new or empty folder: one that holds anything (another dataset, a user's files)
    is refused unless ``force``, because its frames and metadata would be replaced or merged."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "is a file: name a folder for the dataset")
    if out.is_dir() and not force and any(out.iterdir()):
        raise InputError(out, f"folder is not empty ({len(list(out.iterdir()))} entries): its files would be "
                              "replaced. Choose a new or empty folder, or pass --force to write into it")


def model_items(models: Path) -> tuple[MeshItem, ...]:
    """Every model of the BOP dataset (or models folder) ``models`` as an object scenes can draw from (metres)."""
    return tuple(MeshItem(obj_id, m.name, m.mesh) for obj_id, m in bop.load_models(models).items())


def make_scenes(out: Path, categories: list[str], per_category: int, seed: int, width: int = 640,
                height: int = 480, distractors: int | None = None, table_pose: float | None = None,
                force: bool = False, models: Path | None = None, sensor: SensorName = DEFAULT_SENSOR) -> list[dict]:
    """Write ``per_category`` scenes of each category as a BOP dataset in ``out`` (split "test", one image each).

    Scene ids run over ``categories`` in order; each scene's random draw depends only on (seed, category,
    index within the category), so asking for fewer categories leaves the others' scenes unchanged.
    ``distractors`` (a count per scene) and ``table_pose`` (the probability that a frame's scene_camera.json
    gives the table pose) override every category's ``DESKS`` entry.
    -> per scene {"scene_id", "category", "obj_ids", "relations", "visib_fract", "tries"} and, where they differ
    from the paper's set-up, "table_size", "table_pose", "distractors" (also in scenes.json).
    ``models``: a BOP dataset (or models folder) whose models the scenes draw from instead of the built-in
    objects (only ``MODEL_CATEGORIES``; ``SHAPE_CATEGORIES`` need it); copied into ``out`` with their symmetries.
    ``sensor``: the depth sensor's model (``synth.sensor.model.sensor_model``).
    ``out`` must be new or empty unless ``force``.
    """
    check_sensor(sensor)
    unknown = [c for c in categories if c not in CATEGORIES]
    if unknown:
        raise InputError("categories", f"unknown {unknown}; choose from {list(CATEGORIES)}")
    if models is not None and any(c not in MODEL_CATEGORIES for c in categories):
        raise InputError("categories", f"with --models, choose from {list(MODEL_CATEGORIES)}: the others are "
                                       "built from the built-in boxes, can and mug")
    if models is None and any(c in SHAPE_CATEGORIES for c in categories):
        shaped = [c for c in categories if c in SHAPE_CATEGORIES]
        raise InputError("--models", f"{', '.join(shaped)} draw real shapes from given models: pass --models DIR "
                                     "(a BOP dataset or models folder, e.g. ../shared/datasets/ycbv-models)")
    if distractors is not None and distractors < 0:
        raise InputError("distractors", f"must be >= 0, got {distractors}")
    if table_pose is not None and not 0.0 <= table_pose <= 1.0:
        raise InputError("table pose", f"the share of frames that give it must be in [0, 1], got {table_pose}")
    out = Path(out)
    check_out_folder(out, force)
    pool = model_items(models) if models is not None else ()
    for category in dict.fromkeys(c for c in categories if c in SHAPE_CATEGORIES):
        check_models(category, pool)
    cfg = SynthConfig(width=width, height=height, objects=pool, sensor=sensor_model(sensor))
    if models is not None:
        bop.copy_models(models, out, [o.obj_id for o in pool])
    else:
        save_object_models(out)
    _write_camera_json(out, cfg)
    meta = []
    sim = Sim(cfg)
    try:
        for category in categories:
            desk = DESKS.get(category, DeskSpec())
            if distractors is not None:
                desk = replace(desk, distractors=(distractors, distractors))
            if table_pose is not None:
                desk = replace(desk, table_pose=table_pose)
            for j in range(per_category):
                rng = np.random.default_rng([seed, CATEGORIES.index(category), j])
                sample = generate_scene(sim, category, rng, cfg, desk)
                write_scene(out, len(meta), sample, cfg)
                meta.append(_scene_meta(len(meta), sample))
    finally:
        sim.close()
    _write_json(out / "scenes.json", {"scenes": meta})
    return meta


def make_demo(out: Path, seed: int = 0, force: bool = False) -> list[dict]:
    """The bundled demo: two touching boxes on a table, one 640x480 frame (a few hundred kB). ``out`` must be new
    or empty unless ``force``."""
    out = Path(out)
    check_out_folder(out, force)
    cfg = SynthConfig()
    sim = Sim(cfg)
    try:
        sample = generate_scene(sim, "touching", np.random.default_rng([seed, CATEGORIES.index("touching"), 0]), cfg)
    finally:
        sim.close()
    ids = [p.item.obj_id for p in sample.layout]
    save_box_models(out, ids)
    _name_models(out, {p.item.obj_id: p.item.name for p in sample.layout})
    _write_camera_json(out, cfg)
    write_scene(out, 0, sample, cfg)
    meta = [_scene_meta(0, sample)]
    _write_json(out / "scenes.json", {"scenes": meta})
    return meta
