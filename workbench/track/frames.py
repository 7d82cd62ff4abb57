"""A sequence's frames and camera poses, checked before any work: every frame of ``--frames A:B`` present with its
depth, of the first frame's size and on its scale, and, where the camera's motion is given, its pose in
``scene_camera_world.json`` (in millimetres, as BOP's translations)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.geometry import invert_pose
from workbench.io import bop, readers
from workbench.meshes.heavy import announced
from workbench.track.motion import WORLD_FILE, read_world_poses

log = logging.getLogger(__name__)

# A sequence's median depth changes this much at most between frames (a camera moving from 0.3 to 3 m of a table);
# a frame beyond it holds a depth image written on another scale (1000x: metres against millimetres).
MAX_DEPTH_RATIO = 10.0
SATURATED = 65535  # a 16-bit sensor's largest reading: a frame mostly at it measured nothing
# The camera's median step between frames, mm as read: beyond STEP_UM_MM the translations were written in
# micrometres (a 1 cm step reads as 10 m); under STEP_METRES_MM while it turns more than TURN_DEG, in metres.
STEP_UM_MM = 500.0
STEP_METRES_MM = 0.05
TURN_DEG = 0.2


def sequence_world(dataset: Path, scene_id: int, split: str | None, motion: str, frames: list[int]
                   ) -> dict[int, np.ndarray] | None:
    """The scene's camera poses (image id -> ``T_c_w`` (4, 4)) for ``motion`` "given" (InputError when the scene
    has none) or "auto" (None without the file: the motion is registered from the depth); None for "depth".
    InputError naming the file when one of ``frames`` (image ids) has no pose."""
    if motion == "depth":
        return None
    folder = bop.scene_folder(dataset, scene_id, split)
    poses = read_world_poses(folder)
    if poses is None and motion == "given":
        raise InputError(folder / WORLD_FILE, "not found: --motion given needs each frame's camera pose in the world "
                                              "frame (R_w2c, t_w2c mm); use --motion depth to register the camera's "
                                              "motion from the depth instead")
    check_world_poses(poses, frames, folder / WORLD_FILE)
    if poses is not None:
        check_world_units(poses, frames, folder / WORLD_FILE)
    return poses


def check_world_units(world: dict[int, np.ndarray], frames: list[int], path: Path) -> None:
    """A WARNING, once, naming ``path``, when the camera's steps between consecutive frames (its centre, as read in
    mm) say the translations were written in micrometres or metres: each frame would then be re-initialised (~25x
    slower), or the camera's motion taken as none."""
    centres = np.array([invert_pose(world[i])[:3, 3] for i in frames])
    if len(centres) < 2:
        return
    steps_mm = 1000.0 * np.linalg.norm(np.diff(centres, axis=0), axis=1)  # world poses are read as mm -> m
    R = np.array([world[i][:3, :3] for i in frames])
    cos = np.clip((np.einsum("nij,nij->n", R[1:], R[:-1]) - 1.0) / 2.0, -1.0, 1.0)
    turn_deg = float(np.median(np.degrees(np.arccos(cos))))
    step = float(np.median(steps_mm))
    if step > STEP_UM_MM:
        log.warning("%s: the camera moves a median %.3g m between frames: t_w2c looks like micrometres, not "
                    "millimetres (every frame would be estimated again from scratch); divide it by 1000", path,
                    step / 1000.0)
    elif step < STEP_METRES_MM and turn_deg > TURN_DEG:
        log.warning("%s: the camera turns a median %.2g degrees between frames but moves %.2g mm: t_w2c looks like "
                    "metres, not millimetres (the camera's motion would be taken as none); multiply it by 1000",
                    path, turn_deg, step)


def sequence_frames(dataset: Path, scene_id: int, split: str | None, frames: str | None) -> list[int]:
    """The image ids of ``--frames A:B`` (both included; default: all) of one scene, in order. InputError when the
    scene, A or B is not there, when an id between them is missing (a sequence needs every frame) or a frame's
    depth image is."""
    folder = bop.scene_folder(dataset, scene_id, split)
    cam_path = folder / "scene_camera.json"
    ids = sorted(bop.image_ids(readers.read_json(cam_path), cam_path))
    if not ids:
        raise InputError(cam_path, "lists no frames")
    lo, hi = ids[0], ids[-1]
    if frames is not None:
        try:
            lo, hi = (int(v) for v in frames.split(":"))
        except ValueError:
            raise InputError("--frames", f"must be A:B, two image ids (e.g. 1:20), got {frames!r}") from None
        if lo > hi:
            raise InputError("--frames", f"A:B must have A <= B, got {frames}")
        for v in (lo, hi):
            if v not in ids:
                raise InputError("--frames", f"scene {scene_id} has no frame {v} (frames {ids[0]}..{ids[-1]}, "
                                             f"{len(ids)} of them, in {cam_path})")
    chosen = [i for i in ids if lo <= i <= hi]
    gaps = sorted(set(range(lo, hi + 1)) - set(chosen))
    if gaps:
        raise InputError(cam_path, f"frame {gaps[0]} is missing between {lo} and {hi}: a sequence needs every frame; "
                                   f"track the parts either side of it (--frames)")
    for i in chosen:
        if not (folder / "depth" / f"{i:06d}.png").is_file():
            raise InputError(folder / "depth" / f"{i:06d}.png", f"not found: frame {i} of the sequence has no depth")
    check_sequence_depths(folder, chosen)
    return chosen


def check_sequence_depths(folder: Path, frames: list[int]) -> None:
    """Every frame's depth against the first frame's, before the first one runs: its size from the PNG header (one
    camera throughout), then its readings (a few ms a frame): none mostly saturated, none on another scale (its
    median depth within MAX_DEPTH_RATIO of the first frame's). InputError naming the frame and its depth file;
    the first frame's own units are checked when it is loaded, naming its depth_scale."""
    cam_path = folder / "scene_camera.json"
    cams = readers.read_json(cam_path)
    paths = {i: folder / "depth" / f"{i:06d}.png" for i in frames}
    sizes = {i: bop.image_size(paths[i], "depth image") for i in frames}
    first = frames[0]
    for i in frames[1:]:
        if sizes[i] != sizes[first]:
            raise InputError(paths[i], f"frame {i}: the depth image is {sizes[i][0]}x{sizes[i][1]}, but frame "
                                       f"{first}'s is {sizes[first][0]}x{sizes[first][1]}: a sequence's frames come "
                                       "from one camera")
    medians = {}
    with announced(f"checking the depth of {len(frames)} frames", cached=False):
        for i in frames:
            raw = bop.read_depth_png(paths[i])
            valid = raw[raw > 0]
            if valid.size == 0:
                raise InputError(paths[i], f"frame {i}: the depth image has no valid pixel (all zero)")
            if np.mean(valid >= SATURATED) > 0.5:
                raise InputError(paths[i], f"frame {i}: most of the depth image is saturated ({SATURATED}): the "
                                           "sensor measured nothing; leave the frame out (--frames)")
            entry = readers.expect_object(cams.get(str(i)), cam_path, f"image {i}")
            scale = readers.expect_number(entry.get("depth_scale", 1.0), cam_path, f"image {i} depth_scale")
            if scale <= 0:
                raise InputError(cam_path, f"image {i}: depth_scale must be a positive number, got {scale:g}")
            medians[i] = float(np.median(valid)) * scale
    for i in frames[1:]:
        ratio = medians[i] / medians[first]
        if not 1.0 / MAX_DEPTH_RATIO <= ratio <= MAX_DEPTH_RATIO:
            raise InputError(paths[i], f"frame {i}: its median depth is {ratio:.3g}x frame {first}'s "
                                       f"({medians[i] / 1000:.3g} m against {medians[first] / 1000:.3g} m): this "
                                       f"frame's depth image (or its depth_scale in {cam_path.name}) is on another "
                                       "scale than the sequence's first frame")


def check_world_poses(world: dict[int, np.ndarray] | None, frames: list[int], path: Path) -> None:
    """Every frame of the sequence has its camera pose in ``world`` (when there is one): InputError naming
    ``path`` and the first frame without one."""
    if world is not None:
        lacking = [i for i in frames if i not in world]
        if lacking:
            raise InputError(path, f"frame {lacking[0]} has no camera pose (R_w2c, t_w2c); the sequence needs one "
                                   "for every frame (or use --motion depth)")
