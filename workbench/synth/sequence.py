"""Generated sequences (``make-scenes --sequence N``): one generated scene seen from a camera moving on an arc about
its objects, N frames, with each frame's camera pose in a fixed world frame (``scene_camera_world.json``, as the
real sequences of ``ycbv-real-seq`` have it). Optional events: one object pushed along the table from a frame on
(``Push``); one taken out of the scene for some frames and put back where it was (``TakeOut``: absent from those
frames' depth and scene_gt.json); a mug whose handle its body hides comes into view as the camera moves
(``handle_arc``: category ``handle_hidden``, the arc chosen so that the handle shows from a given frame on).

The world frame is deliberately not the table frame (``WORLD_FROM_TABLE``: tilted and shifted), as a robot's base
frame would not be. Frames are written as image ids 0..N-1 of one scene each, in the scene's BOP files.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.geometry import invert_pose, make_pose, rot_x, rot_z
from workbench.io import bop, readers
from workbench.synth.config import CATEGORIES, DESKS, SHAPE_CATEGORIES, DeskSpec, SynthConfig
from workbench.synth.dataset import _scene_meta, _write_camera_json, check_out_folder, save_object_models
from workbench.synth.layout import Placed
from workbench.synth.scenes import SceneSample, generate_scene
from workbench.synth.sensor.model import DEFAULT_SENSOR, SensorName, apply_sensor, check_sensor, sensor_model
from workbench.synth.sim import Sim
from workbench.synth.views import handle_pixels, in_view, render_clean

# The fixed world frame's pose in the table frame: 20 degrees off the table's normal, 0.3 m away.
WORLD_FROM_TABLE = make_pose(rot_x(np.radians(20.0)) @ rot_z(np.radians(35.0)), np.array([0.3, -0.2, 0.1]))


@dataclass(frozen=True)
class Push:
    """From frame ``frame`` (0-based) on, one object that stands on the table with nothing on or against it is
    ``distance`` m further from the others' centre, on the table."""

    frame: int
    distance: float = 0.05


@dataclass(frozen=True)
class TakeOut:
    """On frames ``frame`` (0-based) to ``back - 1`` one object that stands on the table with nothing on or against it
    is out of the scene (lifted away: not in the depth, not in scene_gt.json); from ``back`` on (None: never) it is
    where it was."""

    frame: int
    back: int | None = None

    def out(self, i: int) -> bool:
        return i >= self.frame and (self.back is None or i < self.back)


def arc_cameras(T_cam_world: np.ndarray, centre: np.ndarray, n: int, arc_deg: float) -> np.ndarray:
    """The camera ``T_cam_world`` (4, 4, table frame) turned about the vertical through ``centre`` (3,) m by
    ``arc_deg`` degrees in all, evenly over ``n`` frames (the first as given) -> (n, 4, 4)."""
    out = np.empty((n, 4, 4))
    for i, a in enumerate(np.radians(np.linspace(0.0, arc_deg, n))):
        turn = make_pose(rot_z(a), centre - rot_z(a) @ centre)  # about the vertical through centre
        out[i] = T_cam_world @ invert_pose(turn)
    return out


def pushable(layout: list[Placed]) -> int:
    """The layout index of the object a push moves: the first that stands on the table with nothing on or against
    it. InputError when none does (every object stacked, leaning or carrying another)."""
    carriers = {p.parent for p in layout if p.relation in ("stack", "slant")}  # something rests on or against it
    for k, p in enumerate(layout):
        if p.relation not in ("stack", "slant") and k not in carriers:
            return k
    raise InputError("--push", "no object of this scene stands alone on the table to be pushed; choose another "
                               "category or seed")


def pushed(layout: list[Placed], k: int, distance: float) -> list[Placed]:
    """The layout with object ``k`` moved ``distance`` m along the table, away from the other objects' centre."""
    others = np.mean([p.T[:2, 3] for j, p in enumerate(layout) if j != k], axis=0) if len(layout) > 1 else None
    away = np.array([1.0, 0.0]) if others is None else layout[k].T[:2, 3] - others
    away = away / max(np.linalg.norm(away), 1e-9)
    T = layout[k].T.copy()
    T[:2, 3] += distance * away
    return [replace(p, T=T) if j == k else p for j, p in enumerate(layout)]


# A sequence's mug shows its handle clearly from the event's frame on: on this many times the pixels that make a
# single view's handle "shown" (``SynthConfig.handle_min_shown_px``; at 320x240 that is 15 pixels, which one view
# hardly decides).
SHOWN_FACTOR = 2.5


def handle_arc(cfg: SynthConfig, sample: SceneSample, frames: int, shown: int, step_deg: float = 5.0,
               max_deg: float = 120.0) -> tuple[np.ndarray, float] | None:
    """For a ``handle_hidden`` scene (``sample.layout[0]`` the mug, hidden in the sample's view): the arc about the
    vertical through the mug, turning the camera towards the handle's side, on which frames 0..``shown``-1 hide the
    handle (``SynthConfig.handle_max_hidden_px``) and frames ``shown``.. show it (``SHOWN_FACTOR`` times
    ``handle_min_shown_px``), every object in view on every frame; the smallest such arc in ``step_deg`` steps up
    to ``max_deg`` -> (cameras (N, 4, 4), the arc in degrees, signed), or None when there is none."""
    mug, T0 = sample.layout[0], sample.T_cam_world
    centre = mug.T[:3, 3]
    eye = invert_pose(T0)[:3, 3] - centre
    h = mug.T[:3, 0]  # the handle sticks out along the mug's model +x
    off = np.arctan2(eye[1], eye[0]) - np.arctan2(h[1], h[0]) - np.pi  # the camera's azimuth from straight behind
    sign = 1.0 if np.sin(off) >= 0 else -1.0  # turning further that way brings the handle round into view
    least = SHOWN_FACTOR * cfg.handle_min_shown_px * (cfg.width / 640.0) ** 2

    def handle_px(T: np.ndarray) -> int:
        clean, idx = render_clean(cfg, T, sample.layout, sample.distractors)
        return handle_pixels(cfg, T, mug, clean, idx == 0)

    for arc in np.arange(step_deg, max_deg + step_deg / 2, step_deg):
        a = sign * float(arc)
        cameras = arc_cameras(T0, centre, frames, a)
        # The frames either side of the event first (two renders), then every frame.
        if shown > 0 and handle_px(cameras[shown - 1]) > cfg.handle_max_hidden_px:
            break  # a wider arc only shows it sooner
        if handle_px(cameras[shown]) < least:
            continue
        if all(in_view(cfg, T, sample.layout) for T in cameras) and all(
                (handle_px(T) <= cfg.handle_max_hidden_px) if i < shown else
                (handle_px(T) >= least)
                for i, T in enumerate(cameras) if i not in (shown - 1, shown)):
            return cameras, a
    return None


def write_sequence(out: Path, scene_id: int, sample: SceneSample, cfg: SynthConfig, cameras: np.ndarray,
                   rng: np.random.Generator, push: Push | None = None, split: str = "test",
                   take_out: TakeOut | None = None) -> None:
    """The scene ``sample`` seen from each of ``cameras`` (N, 4, 4, table frame) as frames 0..N-1 of ``scene_id``:
    depth with sensor noise, scene_camera.json (the table pose where the sample gives it), scene_gt.json and
    scene_camera_world.json (world -> camera, R row-major, t mm). ``push``, ``take_out``: the events."""
    moved = None if push is None else pushed(sample.layout, pushable(sample.layout), push.distance)
    gone = None if take_out is None else pushable(sample.layout)
    world = {}
    for i, T in enumerate(cameras):
        layout = moved if moved is not None and i >= push.frame else sample.layout
        if take_out is not None and take_out.out(i):
            layout = [p for k, p in enumerate(layout) if k != gone]
        clean, _ = render_clean(cfg, T, layout, sample.distractors)
        gt = [(p.item.obj_id, T @ p.T) for p in layout]
        bop.save_frame(out, scene_id, i, apply_sensor(clean, rng, cfg.sensor, cfg.K()), cfg.K(),
                       T if sample.table_pose else None, gt, split=split)
        T_c_w = T @ WORLD_FROM_TABLE
        world[str(i)] = {"R_w2c": T_c_w[:3, :3].ravel().tolist(), "t_w2c": (T_c_w[:3, 3] / readers.MM).tolist()}
    path = Path(out) / split / f"{scene_id:06d}" / "scene_camera_world.json"
    path.write_text(json.dumps(world, indent=1) + "\n")


def make_sequences(out: Path, categories: list[str], per_category: int, frames: int, seed: int, width: int = 640,
                   height: int = 480, arc_deg: float = 10.0, push: Push | None = None, force: bool = False,
                   take_out: TakeOut | None = None, handle: int | None = None, max_tries: int = 20,
                   sensor: SensorName = DEFAULT_SENSOR) -> list[dict]:
    """``per_category`` sequences of ``frames`` frames per category, each a generated scene (as ``make_scenes``
    draws it, same seed) seen on an arc of ``arc_deg`` degrees, with an optional ``push`` or ``take_out``. With
    ``handle`` (a frame; category ``handle_hidden`` only) the arc is instead chosen for each scene so that the mug's
    handle, hidden on the first frames, shows from that frame on (``handle_arc``; scenes drawn again, up to
    ``max_tries``, until one has such an arc). -> per scene the metadata ``make_scenes`` gives, with "frames", "arc_deg"
    and the events ("push", "take_out": the object's obj_id and frames; "handle_shown": the frame) added."""
    check_sensor(sensor)
    unknown = [c for c in categories if c not in CATEGORIES]
    if unknown:
        raise InputError("categories", f"unknown {unknown}; choose from {list(CATEGORIES)}")
    shaped = [c for c in categories if c in SHAPE_CATEGORIES]
    if shaped:
        raise InputError("categories", f"{', '.join(shaped)} draw from given models (make-scenes --models), which "
                                       "sequences do not take")
    if frames < 1:
        raise InputError("--sequence", f"must be >= 1 frames, got {frames}")
    if push is not None and not 0 <= push.frame < frames:
        raise InputError("--push", f"the push's frame must be one of the sequence's 0..{frames - 1}, got {push.frame}")
    if take_out is not None and not (0 <= take_out.frame < frames and
                                     (take_out.back is None or take_out.frame < take_out.back < frames)):
        raise InputError("--take-out", f"K:J must have 0 <= K < J <= {frames - 1} (frames 0..{frames - 1}), got "
                                       f"{take_out.frame}:{take_out.back}")
    if handle is not None:
        if not 1 <= handle < frames:
            raise InputError("--handle", f"the frame the handle shows from must be one of 1..{frames - 1}, got "
                                         f"{handle}")
        others = [c for c in categories if c != "handle_hidden"]
        if others:
            raise InputError("--handle", f"turns a hidden mug handle into view: use it with --categories "
                                         f"handle_hidden only, not {', '.join(others)}")
    out = Path(out)
    check_out_folder(out, force)
    cfg = SynthConfig(width=width, height=height, sensor=sensor_model(sensor))
    save_object_models(out)
    _write_camera_json(out, cfg)
    meta, sim = [], Sim(cfg)
    try:
        for category in categories:
            for j in range(per_category):
                rng = np.random.default_rng([seed, CATEGORIES.index(category), j])
                desk = DESKS.get(category, DeskSpec())
                for _ in range(max_tries if handle is not None else 1):
                    sample = generate_scene(sim, category, rng, cfg, desk)
                    if handle is None:
                        centre = np.mean([p.T[:3, 3] for p in sample.layout], axis=0)
                        cameras, arc = arc_cameras(sample.T_cam_world, centre, frames, arc_deg), arc_deg
                        break
                    found = handle_arc(sim.cfg, sample, frames, handle)
                    if found is not None:
                        cameras, arc = found
                        break
                else:
                    raise InputError("--handle", f"no {category} scene in {max_tries} draws had an arc that shows the "
                                                 f"mug's handle from frame {handle} on; try another --seed or frame")
                write_sequence(out, len(meta), sample, sim.cfg, cameras, rng, push, take_out=take_out)
                entry = {**_scene_meta(len(meta), sample), "frames": frames, "arc_deg": round(float(arc), 3)}
                if push is not None:
                    entry["push"] = {"obj_id": sample.layout[pushable(sample.layout)].item.obj_id,
                                     "frame": push.frame, "distance_m": push.distance}
                if take_out is not None:
                    entry["take_out"] = {"obj_id": sample.layout[pushable(sample.layout)].item.obj_id,
                                         "frame": take_out.frame, "back": take_out.back}
                if handle is not None:
                    entry["handle_shown"] = handle
                meta.append(entry)
    finally:
        sim.close()
    (out / "scenes.json").write_text(json.dumps({"scenes": meta}, indent=2) + "\n")
    return meta
