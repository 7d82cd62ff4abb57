"""What a BOP dataset says of its ground truth besides the poses: how much of each object the camera sees
(scene_gt_info.json's ``visib_fract``) and, in sets `workbench make-scenes` wrote, each scene's category
(scenes.json). ``bench`` and ``score`` both report by them."""

from __future__ import annotations

from pathlib import Path

from workbench.errors import InputError
from workbench.io import bop, readers
from workbench.problem.scene import Frame

# visib_fract below this: the object counts as hidden. BOP's test targets leave such objects out (the depth hardly
# constrains them: the estimate of a hidden object is the physics' and the posterior's guess).
HIDDEN_VISIB = 0.1


def gt_info_path(frame: Frame) -> Path:
    """The scene_gt_info.json beside the frame's scene_gt.json (it may not exist)."""
    return Path(frame.source).parents[1] / "scene_gt_info.json"


def visib_fractions(frame: Frame) -> list[float]:
    """scene_gt_info.json visib_fract per object of the frame (same order as scene_gt.json)."""
    path = gt_info_path(frame)
    content = readers.read_json(path)
    bop.image_ids(content, path)
    info = readers.expect_list(content.get(str(frame.im_id)), path, f"image {frame.im_id}")
    fractions = [readers.expect_number(readers.expect_object(i, path, "an object entry").get("visib_fract"), path,
                                   f"image {frame.im_id} visib_fract") for i in info]
    if len(fractions) != len(frame.object_ids):
        raise InputError(path, f"image {frame.im_id}: {len(fractions)} entries for {len(frame.object_ids)} objects")
    return fractions


def scenes_path(dataset: Path) -> Path:
    """The scenes.json `workbench make-scenes` writes at a set's root (other sets have none)."""
    return Path(dataset) / "scenes.json"


def scene_categories(dataset: Path) -> dict[int, str]:
    """scene_id -> category, from ``scenes_path(dataset)``."""
    path = scenes_path(dataset)
    meta = readers.expect_object(readers.read_json(path), path, "the file")
    out = {}
    for s in readers.expect_list(meta.get("scenes"), path, "scenes"):
        s = readers.expect_object(s, path, "a scene")
        out[readers.expect_int(s.get("scene_id"), path, "scene_id")] = s.get("category")
        if not isinstance(out[s["scene_id"]], str):
            raise InputError(path, f"scene {s['scene_id']}: category must be a string, got {s.get('category')!r:.40}")
    return out
