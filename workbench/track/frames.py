"""A sequence's frames and camera poses, checked before any work: every frame of ``--frames A:B`` present with its
depth, and, where the camera's motion is given, its pose in ``scene_camera_world.json``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.io import bop, readers
from workbench.track.motion import WORLD_FILE, read_world_poses


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
    return poses


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
    return chosen


def check_world_poses(world: dict[int, np.ndarray] | None, frames: list[int], path: Path) -> None:
    """Every frame of the sequence has its camera pose in ``world`` (when there is one): InputError naming
    ``path`` and the first frame without one."""
    if world is not None:
        lacking = [i for i in frames if i not in world]
        if lacking:
            raise InputError(path, f"frame {lacking[0]} has no camera pose (R_w2c, t_w2c); the sequence needs one "
                                   "for every frame (or use --motion depth)")
