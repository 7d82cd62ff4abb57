"""A sequence's labels: one pose per still object in the sequence's world frame, carried to every frame by the
camera's motion, and written as BOP files.

The world frame is the table frame of the sequence as ``workbench track`` keeps it (the first frame's table, moved
by the camera's motion): each frame's camera pose in it is ``T_cam_world[im_id]``. An object's label holds from its
``first`` to its ``last`` frame (an object taken out ends there) and may move: ``moves`` maps a frame to the pose it
has from that frame on.

Files (BOP, camera frame, R row-major, t in mm):
- the labels: ``scene_gt_labels.json`` beside the scene's scene_gt.json (or a path given), or the scene's own
  scene_gt.json only with ``overwrite_original`` (a backup kept first, as one frame's labels are saved);
- ``scene_gt_info.json``'s form (visible fraction, boxes, pixel counts; rendered) beside it:
  ``scene_gt_info_labels.json``, or the scene's scene_gt_info.json (backed up) with ``overwrite_original``;
- ``label_provenance.json``: which frames a person checked and which were propagated, and every frame's check.
Every image's entry is merged (``frame.merge_entries``): objects the labels do not hold keep their entries.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.geometry import check_rigid, rotation_angle
from workbench.io import readers
from workbench.io.outputs import write_file
from workbench.io.readers import MM
from workbench.label.check import ObjectCheck
from workbench.label.frame import ORIGINAL_FILE, _backup, _scene_dir, check_scene_gt, merge_entries

LABELS_FILE = "scene_gt_labels.json"
INFO_FILE, INFO_LABELS_FILE = "scene_gt_info.json", "scene_gt_info_labels.json"
PROVENANCE_FILE = "label_provenance.json"
PROVENANCE_FORMAT = 1


@dataclass
class ObjectLabel:
    """One object's label through a sequence: ``T_world_obj`` (4, 4), from frame ``first`` to ``last`` (None: the
    sequence's start / end); ``moves``: frame -> (4, 4) pose from that frame on."""

    obj_id: int
    T_world_obj: np.ndarray
    first: int | None = None
    last: int | None = None
    moves: dict[int, np.ndarray] = field(default_factory=dict)

    def pose_at(self, im_id: int) -> np.ndarray | None:
        """The label's (4, 4) world pose in frame ``im_id``, None outside [first, last]."""
        if (self.first is not None and im_id < self.first) or (self.last is not None and im_id > self.last):
            return None
        since = [f for f in self.moves if f <= im_id]
        return self.moves[max(since)] if since else self.T_world_obj


@dataclass
class SequenceLabels:
    """A scene's labels: ``objects`` in the frames' object order, each frame's camera ``T_cam_world`` (image id ->
    (4, 4), world -> camera), and the frames a person ``checked``."""

    scene_id: int
    T_cam_world: dict[int, np.ndarray]
    objects: list[ObjectLabel]
    checked: set[int] = field(default_factory=set)

    @property
    def frames(self) -> list[int]:
        return sorted(self.T_cam_world)

    @property
    def obj_ids(self) -> list[int]:
        return [o.obj_id for o in self.objects]

    def world_poses(self, im_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``im_id``'s labels -> (T_world_obj (K, 4, 4), identity where absent; present (K,) bool)."""
        poses = [o.pose_at(im_id) for o in self.objects]
        present = np.array([p is not None for p in poses])
        return np.array([np.eye(4) if p is None else p for p in poses]), present

    def camera_poses(self, im_id: int) -> list[np.ndarray | None]:
        """Frame ``im_id``'s labels in its camera frame: per object T_cam_obj (4, 4), or None where absent."""
        T_cw = self.T_cam_world[im_id]
        return [None if (p := o.pose_at(im_id)) is None else T_cw @ p for o in self.objects]

    def moved_to(self, k: int, im_id: int, T_world_obj: np.ndarray) -> None:
        """Object ``k`` has pose ``T_world_obj`` (4, 4) from frame ``im_id`` on (a person moved it there)."""
        T = check_rigid(np.asarray(T_world_obj, dtype=np.float64), f"label of object {self.objects[k].obj_id}")
        o = self.objects[k]
        if im_id == self.frames[0] and not o.moves:
            o.T_world_obj = T
        else:
            o.moves[im_id] = T

    def ends_at(self, k: int, im_id: int) -> None:
        """Object ``k`` is gone after frame ``im_id`` (taken out): its label ends there."""
        self.objects[k].last = im_id


def labels_json(labels: SequenceLabels) -> dict:
    """-> the plain JSON object a session keeps (``SequenceRecord.labels``): poses as 4 x 4 lists, m; frames keyed by
    their image ids as text."""
    return {
        "scene_id": labels.scene_id,
        "cameras": {str(i): T.tolist() for i, T in sorted(labels.T_cam_world.items())},
        "objects": [{"obj_id": o.obj_id, "T_world_obj": o.T_world_obj.tolist(), "first": o.first, "last": o.last,
                     "moves": {str(i): T.tolist() for i, T in sorted(o.moves.items())}} for o in labels.objects],
        "checked": sorted(labels.checked),
    }


def parse_labels(data: dict, where: str = "sequence.labels") -> SequenceLabels:
    """``labels_json``'s object -> the labels; ValueError naming the entry at fault (a hand-edited or corrupt
    session)."""
    def frame(key, at: str) -> int:
        if not str(key).isdigit():
            raise ValueError(f"{at}: {key!r} is no image id (a whole number >= 0)")
        return int(key)

    def optional(v, at: str) -> int | None:
        return None if v is None else readers.integer(v, at)

    def label(o: dict, at: str) -> ObjectLabel:
        moves = {frame(k, f"{at}.moves"): readers.pose(v, f"{at}.moves[{k}]") for k, v in o["moves"].items()}
        return ObjectLabel(readers.integer(o["obj_id"], f"{at}.obj_id"),
                           readers.pose(o["T_world_obj"], f"{at}.T_world_obj"),
                           optional(o["first"], f"{at}.first"), optional(o["last"], f"{at}.last"), moves)

    try:
        cams = {frame(k, f"{where}.cameras"): readers.pose(v, f"{where}.cameras[{k}]")
                for k, v in data["cameras"].items()}
        objects = [label(o, f"{where}.objects[{n}]") for n, o in enumerate(data["objects"])]
        checked = {frame(i, f"{where}.checked") for i in data["checked"]}
        scene_id = readers.integer(data["scene_id"], f"{where}.scene_id")
    except (KeyError, TypeError, AttributeError) as e:
        raise ValueError(f"{where} is malformed ({type(e).__name__}: {e})") from e
    if not cams:
        raise ValueError(f"{where}.cameras: no frames")
    return SequenceLabels(scene_id, cams, objects, checked)


# ----------------------------------------------------------------------------------------------------------------
# BOP entries


def gt_entries(labels: SequenceLabels, im_id: int) -> list[dict | None]:
    """Frame ``im_id``'s scene_gt entries, one per object (None where its label does not hold)."""
    out = []
    for obj_id, T in zip(labels.obj_ids, labels.camera_poses(im_id)):
        out.append(None if T is None else {"cam_R_m2c": T[:3, :3].ravel().tolist(),
                                           "cam_t_m2c": (T[:3, 3] / MM).tolist(), "obj_id": int(obj_id)})
    return out


def gt_info_entry(alone: np.ndarray, observed: np.ndarray, delta_m: float = 0.015) -> dict:
    """One object's scene_gt_info.json entry from its depth drawn alone (H, W) and the observed depth (H, W),
    full-resolution camera z in metres (0 = none): BOP's pixel counts, boxes [x, y, w, h] and visible fraction,
    visible where it is not behind the observation by more than ``delta_m`` or the sensor saw nothing."""
    drawn = alone > 0
    visible = drawn & ((observed == 0) | (alone <= observed + delta_m))
    n_all, n_visib = int(drawn.sum()), int(visible.sum())

    def box(mask: np.ndarray) -> list[int]:
        if not mask.any():
            return [-1, -1, -1, -1]
        ys, xs = np.nonzero(mask)
        return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]

    return {"bbox_obj": box(drawn), "bbox_visib": box(visible), "px_count_all": n_all,
            "px_count_valid": int((drawn & (observed > 0)).sum()), "px_count_visib": n_visib,
            "visib_fract": n_visib / n_all if n_all else 0.0}


# ----------------------------------------------------------------------------------------------------------------
# Files


@dataclass(frozen=True)
class LabelFiles:
    """Where a sequence's labels go: ``labels`` (scene_gt form), ``info`` (scene_gt_info form), ``provenance``."""

    labels: Path
    info: Path
    provenance: Path
    overwrite_original: bool = False


def label_files(dataset: Path, scene_id: int, split: str | None = None, path: Path | None = None,
                overwrite_original: bool = False) -> LabelFiles:
    """The files ``write_sequence`` writes: by default scene_gt_labels.json, scene_gt_info_labels.json and
    label_provenance.json in the scene's folder; ``path`` for the labels (the other two beside it, named after it);
    with ``overwrite_original`` the scene's own scene_gt.json and scene_gt_info.json. A ``path`` naming the
    dataset's own files without ``overwrite_original`` is refused."""
    scene_dir = _scene_dir(dataset, scene_id, split)
    if overwrite_original:
        if path is not None:
            raise InputError(path, f"overwriting the ground truth writes the scene's own {scene_dir / ORIGINAL_FILE}"
                                   ", not another file")
        return LabelFiles(scene_dir / ORIGINAL_FILE, scene_dir / INFO_FILE, scene_dir / PROVENANCE_FILE, True)
    if path is None:
        return LabelFiles(scene_dir / LABELS_FILE, scene_dir / INFO_LABELS_FILE, scene_dir / PROVENANCE_FILE)
    path = Path(path)
    for own in (ORIGINAL_FILE, INFO_FILE):
        if path.name == own or path.resolve() == (scene_dir / own).resolve():
            raise InputError(path, "this is a dataset's original ground truth; pass --overwrite-gt to replace it (a "
                                   "backup is kept) or write the labels elsewhere")
    return LabelFiles(path, path.with_name(f"{path.stem}_info.json"), path.with_name(f"{path.stem}_provenance.json"))


def read_keyed(path: Path) -> dict:
    """A scene_gt-form file (image id -> list of objects), empty when missing; InputError naming it otherwise (the
    check ``write_sequence`` makes before it writes, which ``workbench label`` makes before it tracks)."""
    content = readers.read_json(path) if path.is_file() else {}
    if not isinstance(content, dict):
        raise InputError(path, "expected a JSON object keyed by image id")
    return check_scene_gt(content, path)


def merged_frame(old_gt: list[dict], old_info: list[dict], obj_ids: list[int], gt: list[dict | None],
                 info: list[dict | None]) -> tuple[list[dict], list[dict]]:
    """One image's scene_gt and scene_gt_info entries with the labels merged in (``frame.merge_entries``'s rule):
    the two lists stay aligned, as BOP pairs them by position. An entry kept from before keeps its old info; where
    the old info file lacked it, the entry says nothing is known to be visible (``visib_fract`` 0, boxes -1)."""
    marked = merge_entries(old_gt, obj_ids, [None if e is None else {"obj_id": e["obj_id"], "_label": k}
                                             for k, e in enumerate(gt)])
    out_gt, out_info = [], []
    for j, e in enumerate(marked):
        k = e.get("_label")
        out_gt.append(old_gt[j] if k is None else gt[k])
        kept = old_info[j] if j < len(old_info) and len(old_info) == len(old_gt) else None
        out_info.append(info[k] if k is not None and info[k] is not None else kept or _UNKNOWN_INFO)
    return out_gt, out_info


_UNKNOWN_INFO = {"bbox_obj": [-1, -1, -1, -1], "bbox_visib": [-1, -1, -1, -1], "px_count_all": 0,
                 "px_count_valid": 0, "px_count_visib": 0, "visib_fract": 0.0}


def write_sequence(files: LabelFiles, labels: SequenceLabels, infos: dict[int, list[dict | None]],
                   checks: dict[int, list[ObjectCheck]], rest_shift: np.ndarray | None = None) -> list[Path]:
    """Write every frame's labels, their scene_gt_info entries (``infos``: image id -> per object an entry or None)
    and the provenance with each frame's ``checks`` and how far physics would move each label to rest
    (``rest_shift`` (K,) metres, if known) -> the files written. Nothing is written when an existing file
    cannot be merged into (InputError naming it); the originals are backed up before they are replaced."""
    gt, info = read_keyed(files.labels), read_keyed(files.info)
    for i in labels.frames:
        empty = [None] * len(labels.objects)
        gt[str(i)], info[str(i)] = merged_frame(gt.get(str(i), []), info.get(str(i), []), labels.obj_ids,
                                                gt_entries(labels, i), infos.get(i, empty))
    if files.overwrite_original:
        for path in (files.labels, files.info):
            if path.exists():
                _backup(path)
    for path, content in ((files.labels, gt), (files.info, info)):
        write_file(path, json.dumps({k: content[k] for k in sorted(content, key=int)}, indent=1).encode())
    write_file(files.provenance, json.dumps(provenance(labels, checks, rest_shift), indent=1).encode())
    return [files.labels, files.info, files.provenance]


def provenance(labels: SequenceLabels, checks: dict[int, list[ObjectCheck]], rest_shift: np.ndarray | None = None
               ) -> dict:
    """The provenance file's content: per frame whether a person checked it or it was propagated, whether it is
    flagged and each object's check; per object the frames its label holds, the frames where it moves and how far
    physics would move it to rest (``rest_shift_mm``, null where not known)."""
    frames = {}
    for i in labels.frames:
        rows = checks.get(i, [])
        frames[str(i)] = {"source": "checked" if i in labels.checked else "propagated",
                          "flagged": any(c.flagged for c in rows), "objects": [c.to_dict() for c in rows]}
    shifts = [None] * len(labels.objects) if rest_shift is None else [round(1000 * float(m), 1) for m in rest_shift]
    objects = [{"obj_id": o.obj_id, "first": o.first, "last": o.last, "moves_at": sorted(o.moves),
                "rest_shift_mm": m} for o, m in zip(labels.objects, shifts)]
    return {"format": PROVENANCE_FORMAT, "scene_id": labels.scene_id,
            "written": datetime.now(timezone.utc).isoformat(timespec="seconds"), "objects": objects, "frames": frames}


def from_frame_poses(scene_id: int, T_cam_world: dict[int, np.ndarray], obj_ids: list[int],
                     poses: dict[int, list[np.ndarray | None]], tol_m: float = 1e-3, tol_deg: float = 0.5
                     ) -> SequenceLabels:
    """Labels read back frame by frame (``poses``: image id -> per object a (4, 4) world pose or None, as
    ``frame.load_labels`` reads a saved file) as one ``SequenceLabels``: each object's label from the first frame
    that has it to the last, its pose where it starts, and a move wherever its world pose changes by more than
    ``tol_m`` metres or ``tol_deg`` degrees (a saved file's millimetres round the poses). A frame without the
    object's entry inside that span keeps the pose before it. InputError when no frame labels an object."""
    frames = sorted(T_cam_world)
    objects = []
    for k, obj_id in enumerate(obj_ids):
        held = [(i, np.asarray(poses[i][k], dtype=np.float64)) for i in frames
                if i in poses and poses[i][k] is not None]
        if not held:
            raise InputError(f"object {obj_id}", f"no frame of scene {scene_id} (frames {frames[0]}..{frames[-1]}) "
                                                 "has a saved label for it")
        first, last = held[0][0], held[-1][0]
        label = ObjectLabel(int(obj_id), held[0][1], None if first == frames[0] else first,
                            None if last == frames[-1] else last)
        current = held[0][1]
        for i, T in held[1:]:
            turn_deg = np.degrees(rotation_angle(current[:3, :3].T @ T[:3, :3]))
            if np.linalg.norm(T[:3, 3] - current[:3, 3]) > tol_m or turn_deg > tol_deg:
                label.moves[i], current = T, T
        objects.append(label)
    return SequenceLabels(scene_id, {i: np.asarray(T_cam_world[i], dtype=np.float64) for i in frames}, objects)
