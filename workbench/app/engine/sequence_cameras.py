"""The camera poses of a sequence's frames in its table frame, for the frames the workbench's timeline has not
processed (``engine.label_sequence`` checks labels on every frame): from the dataset where it gives them, else
registered from the depth, as ``workbench track`` moves its table frame from frame to frame (``track.motion``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from workbench.errors import InputError


def sequence_cameras(dataset: Path, scene_id: int, split: str | None, frames: list[int],
                     known: dict[int, np.ndarray], region: tuple[np.ndarray, np.ndarray]) -> dict[int, np.ndarray]:
    """Each of ``frames``' camera pose ``T_cam_world`` (4, 4) in the sequence's table frame: ``known``'s (the
    processed frames', image id -> (4, 4), at least one), else the table pose the dataset gives the frame, else the
    known frame's moved by the camera's motion between them (``scene_camera_world.json``), else registered from the
    depth to the nearest frame whose pose is found (``track.motion.depth_motion``, ``region`` the object region
    (lo, hi) (2,) m of the table frame)."""
    from workbench.io import bop
    from workbench.track.motion import depth_motion, given_motion, read_world_poses

    if not known:
        raise InputError("sequence", "no frame of the sequence is processed: load one of its frames")
    world = read_world_poses(bop.scene_folder(dataset, scene_id, split))
    out = {i: np.asarray(T, dtype=np.float64) for i, T in known.items() if i in frames}
    anchor = min(known, key=lambda i: (i not in frames, i))
    loaded: dict[int, object] = {}

    def frame(i: int):
        if i not in loaded:
            loaded[i] = bop.load_frame(dataset, scene_id, i, split)
        return loaded[i]

    # Outward from the processed frames, so that a registered pose always has a found neighbour.
    todo = sorted((i for i in frames if i not in out), key=lambda i: min(abs(i - j) for j in known))
    for i in todo:
        given = frame(i).camera.T_cam_world
        if given is not None:
            out[i] = np.asarray(given, dtype=np.float64)
        elif world is not None and anchor in world and i in world:
            out[i] = given_motion(world[anchor], world[i]) @ known[anchor]
        else:
            j = min(out, key=lambda j: abs(i - j))
            out[i] = depth_motion(frame(j), frame(i), out[j], region) @ out[j]
    return {i: out[i] for i in frames}
