"""Ground-truth labelling: put a labelled scene at rest, fit it to the depth, show where it disagrees, compare an
estimate with it, and save it in BOP's scene_gt.json form.

Labels are (K, 4, 4) T_world_obj in the table frame, one per object of the problem (NaN rows, or None entries,
for objects not labelled yet). The functions that render or simulate accept the caller's ``LocalEvaluator`` so
that an app reuses its renderer and physics client instead of creating new ones per click.

Files: labels go to ``scene_gt_labels.json`` beside the scene's scene_gt.json by default (same format: per image a
list of {"cam_R_m2c": 9 numbers row-major, "cam_t_m2c": 3 numbers in mm, "obj_id"}), so that the dataset's own
ground truth is never touched unless asked for; then a timestamped backup is kept, which ``restore_backup`` puts
back (``list_backups`` lists them).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.evaluation import LocalEvaluator
from workbench.geometry import check_rigid, invert_pose
from workbench.inference.answer.settle import pattern_search
from workbench.io import bop, readers
from workbench.io.outputs import write_file
from workbench.io.readers import MM
from workbench.problem.problem import Problem
from workbench.render.likelihood import scene_loglik
from workbench.score.metrics import add_s, model_points, position_error, rotation_error

LABELS_FILE = "scene_gt_labels.json"
ORIGINAL_FILE = "scene_gt.json"
BACKUP_PREFIX = f"{ORIGINAL_FILE}.bak-"
STAMP_FORMAT = "%Y%m%dT%H%M%S%f"  # a backup's name: scene_gt.json.bak-<stamp>


def _scene(problem: Problem, T_world_obj) -> np.ndarray:
    """Labels (K, 4, 4) as float64, refused unless finite rigid poses (a reflection is not a pose)."""
    T = np.array(T_world_obj, dtype=np.float64)
    if T.shape != (problem.n_objects, 4, 4) or not np.all(np.isfinite(T)):
        raise InputError("labels", f"expected finite poses of shape ({problem.n_objects}, 4, 4), got {T.shape}")
    return check_rigid(T, "labels")


@contextmanager
def _evaluator(problem: Problem, evaluator: LocalEvaluator | None):
    """The caller's LocalEvaluator, or a new one closed on exit."""
    if evaluator is not None:
        yield evaluator
        return
    own = LocalEvaluator(problem)
    try:
        yield own
    finally:
        own.close()


# ----------------------------------------------------------------------------------------------------------------
# Plausibility, fitting, residuals


def snap_to_plausible(problem: Problem, T_world_obj: np.ndarray, evaluator: LocalEvaluator | None = None
                      ) -> tuple[np.ndarray, np.ndarray, int]:
    """Let physics put the labelled scene (K, 4, 4) at rest -> (resting poses (K, 4, 4), how far each object's
    origin moved (K,) metres, physics status code; see ``physics.STATUS_NAMES``). A scene the simulation cannot
    settle (status unstable) comes back unchanged."""
    T = _scene(problem, T_world_obj)
    with _evaluator(problem, evaluator) as ev:
        projected, status, _ = ev.projector.project(T)
    moved = np.linalg.norm(projected[:, :3, 3] - T[:, :3, 3], axis=-1)
    return projected, moved, int(status)


def scene_logliks(problem: Problem, evaluator: LocalEvaluator, scenes: np.ndarray) -> np.ndarray:
    """Log-likelihood of scenes (B, K, 4, 4) exactly as given, without physics -> (B,)."""
    rendered = evaluator.renderer.render(scenes)
    return scene_loglik(problem.observed, problem.background, rendered, problem.config.likelihood, problem.clutter)


def fit_label(problem: Problem, T_world_obj: np.ndarray, evaluator: LocalEvaluator | None = None,
              step_m: float = 0.01, step_deg: float = 4.0, min_step_m: float = 5e-4, max_rounds: int = 80,
              snap: bool = True) -> np.ndarray:
    """Refine a labelled scene (K, 4, 4) against the observed depth, then (``snap``) let physics put it at rest
    -> (K, 4, 4).

    ``settle.pattern_search`` on the likelihood of the scene as given (no physics while fitting, so every small
    move counts), with no bound on how far it goes. Local: it refines a label within about two steps of the truth,
    it does not find one."""
    T = _scene(problem, T_world_obj)
    with _evaluator(problem, evaluator) as ev:
        T, _, _ = pattern_search(T, lambda scenes: scene_logliks(problem, ev, scenes), step_m, step_deg, min_step_m,
                                 max_rounds)
        if snap:
            T, _, _ = snap_to_plausible(problem, T, ev)
    return T


def residual_map(problem: Problem, evaluator: LocalEvaluator, T_world_obj: np.ndarray) -> np.ndarray:
    """Per-pixel log-likelihood (h, w) float32 of the scene (K, 4, 4) as given, on the problem's render grid
    (``problem.render_camera``, the crop ``problem.roi`` of the image); 0 where the sensor gave no reading. Low
    values mark where the label disagrees with the depth."""
    _, pixels = evaluator.explain(_scene(problem, T_world_obj))
    return pixels


def label_errors(problem: Problem, estimate: np.ndarray, label) -> list[dict]:
    """Per object, how far ``estimate`` (K, 4, 4) is from ``label`` ((K, 4, 4) with NaN rows, or a list with None,
    for unlabelled objects): {"obj_id", "position_error_m", "rotation_error_deg" (symmetry-aware), "add_s_m"},
    the errors None where there is no label."""
    out = []
    for k, model in enumerate(problem.models):
        L = None if label[k] is None else np.asarray(label[k], dtype=np.float64)
        row = {"obj_id": model.obj_id, "position_error_m": None, "rotation_error_deg": None, "add_s_m": None}
        if L is not None and np.all(np.isfinite(L)):
            E = np.asarray(estimate[k], dtype=np.float64)
            row.update(position_error_m=position_error(L, E, model.symmetries),
                       rotation_error_deg=rotation_error(L, E, model.symmetries),
                       add_s_m=add_s(L, E, model_points(model.mesh)))
        out.append(row)
    return out


# ----------------------------------------------------------------------------------------------------------------
# Files


def _scene_dir(dataset: Path, scene_id: int, split: str | None) -> Path:
    return bop._scene_dir(bop._split_dir(Path(dataset), split), scene_id)


def labels_path(dataset: Path, scene_id: int, split: str | None = None) -> Path:
    """Where ``save_labels`` writes by default: scene_gt_labels.json in the scene's folder."""
    return _scene_dir(dataset, scene_id, split) / LABELS_FILE


def save_labels(dataset: Path, scene_id: int, im_id: int, T_cam_world: np.ndarray, labels, obj_ids: list[int],
                path: Path | None = None, overwrite_original: bool = False, split: str | None = None) -> Path:
    """Write the labels (per object a (4, 4) T_world_obj, or None for an object not labelled) of image ``im_id`` in
    BOP scene_gt.json form (camera frame, R row-major, t in mm) -> the file written. By default
    ``scene_gt_labels.json`` beside the scene's scene_gt.json, or ``path``.

    The image's entry is merged, never replaced whole (``merge_entries``): a labelled object replaces its own entry
    and every other entry (objects not labelled, objects outside the problem) stays as it was, so that labelling one
    object of a frame never drops the truth of the others.

    A file named scene_gt.json is written only with ``overwrite_original`` (then the scene's own, after copying it
    to scene_gt.json.bak-<timestamp>); scene_gt_info.json is not updated and may no longer match."""
    scene_dir = _scene_dir(dataset, scene_id, split)
    original = scene_dir / ORIGINAL_FILE
    if overwrite_original:
        if path is not None and Path(path).resolve() != original.resolve():
            raise InputError(path, f"overwrite_original writes the scene's own {original}, not another file")
        target = original
    else:
        target = scene_dir / LABELS_FILE if path is None else Path(path)
        if target.name == ORIGINAL_FILE or target.resolve() == original.resolve():
            raise InputError(target, "this is a dataset's original ground truth; pass overwrite_original=True to "
                                     "replace it (a backup is kept) or write the labels elsewhere")
    if len(labels) != len(obj_ids):
        raise InputError("labels", f"{len(labels)} labels for {len(obj_ids)} objects")
    T_cam_world = check_rigid(T_cam_world, "T_cam_world")
    entries: list[dict | None] = []
    for obj_id, T in zip(obj_ids, labels):
        if T is None or not np.all(np.isfinite(T)):
            entries.append(None)
            continue
        T_cam_obj = T_cam_world @ check_rigid(T, f"label of object {obj_id}")
        entries.append({"cam_R_m2c": T_cam_obj[:3, :3].ravel().tolist(), "cam_t_m2c": (T_cam_obj[:3, 3] / MM).tolist(),
                        "obj_id": int(obj_id)})
    old_entries = _image_entries(target, im_id)
    if not all(isinstance(e, dict) for e in old_entries):  # merged into, so every entry must be an object
        raise InputError(target, f"image {im_id}: expected a list of objects")
    if overwrite_original and original.exists():
        _backup(original)
    bop._merge_json(target, im_id, merge_entries(old_entries, list(obj_ids), entries))
    return target


def _image_entries(path: Path, im_id: int) -> list:
    """The entry of image ``im_id`` in the scene_gt-form file ``path`` (none if the file or image is missing);
    InputError naming the file where the file is not keyed by image or the entry is not a list."""
    if not path.is_file():
        return []
    content = readers.read_json(path)
    if not isinstance(content, dict):
        raise InputError(path, "expected a JSON object keyed by image id")
    entries = content.get(str(im_id), [])
    if not isinstance(entries, list):
        raise InputError(path, f"image {im_id}: expected a list of objects")
    return entries


def merge_entries(old: list[dict], obj_ids: list[int], new: list[dict | None]) -> list[dict]:
    """An image's scene_gt entry with the labels merged in: the n-th instance of an object in ``obj_ids`` is the
    n-th entry of that ``obj_id`` in ``old`` (as ``load_labels`` reads them); a label (``new[k]`` not None)
    replaces that entry in place, or is appended where the image had none; every other entry is kept as it was."""
    out = list(old)
    seen: dict[int, int] = {}
    for obj_id, entry in zip(obj_ids, new):
        n = seen.get(obj_id, 0)
        seen[obj_id] = n + 1
        if entry is None:
            continue
        slots = [j for j, e in enumerate(out) if e.get("obj_id") == obj_id]
        if n < len(slots):
            out[slots[n]] = entry
        else:
            out.append(entry)
    return out


def check_scene_gt(content, path: Path) -> dict:
    """``content`` read from ``path`` as scene_gt.json's form -> itself: keyed by image ids, each a list of objects;
    InputError naming ``path`` and the first image that is not."""
    bop.image_ids(content, path)
    for key, entries in content.items():
        if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
            raise InputError(path, f"image {key}: expected a list of objects")
    return content


def _backup(path: Path) -> Path:
    """Copy ``path`` to <name>.bak-<timestamp>, never replacing an earlier backup."""
    stamp = datetime.now().strftime(STAMP_FORMAT)
    backup = path.with_name(f"{path.name}.bak-{stamp}")
    with open(backup, "xb") as f:
        f.write(path.read_bytes())
    return backup


def kept_note(path: Path, since: float) -> str:
    """What a save that replaced ``path`` kept of it, in words: its newest backup (``<name>.bak-<stamp>``) written
    at or after ``since`` (``time.time()``; a second's slack for file systems' coarse times), or that there was no
    original to keep."""
    backups = [b for b in path.parent.glob(f"{path.name}.bak-*") if b.stat().st_mtime >= since - 1]
    return f"the original was kept as `{max(backups).name}`" if backups else "there was no original to keep"


@dataclass(frozen=True)
class Backup:
    """A backup of a scene's scene_gt.json (``path``) and when it was made (``time``: from its name's stamp, else
    the file's modification time)."""

    path: Path
    time: datetime


def list_backups(dataset: Path, scene_id: int, split: str | None = None) -> list[Backup]:
    """The backups ``save_labels`` (and ``restore_backup``) kept of the scene's scene_gt.json, newest first."""
    out = []
    for path in _scene_dir(dataset, scene_id, split).glob(f"{BACKUP_PREFIX}*"):
        if not path.is_file():
            continue
        try:
            time = datetime.strptime(path.name[len(BACKUP_PREFIX):], STAMP_FORMAT)
        except ValueError:  # renamed or copied by hand: when it was last written
            time = datetime.fromtimestamp(path.stat().st_mtime)
        out.append(Backup(path, time))
    return sorted(out, key=lambda b: (b.time, b.path.name), reverse=True)


def restore_backup(dataset: Path, scene_id: int, name: str, split: str | None = None) -> tuple[Path, Path | None]:
    """Put the backup ``name`` (a file name from ``list_backups``) back as the scene's scene_gt.json, byte for byte
    -> (scene_gt.json, the backup kept of the scene_gt.json it replaced, None when there was none). Nothing is lost:
    the current scene_gt.json is backed up first, as ``save_labels`` does, and the backup is written atomically.
    InputError naming the file, with nothing written, for a name that is not one of the scene's backups or a
    backup that is not scene_gt.json's form (JSON keyed by image ids, each a list of objects)."""
    scene_dir = _scene_dir(dataset, scene_id, split)
    backup = scene_dir / str(name)
    if Path(str(name)).name != str(name) or not str(name).startswith(BACKUP_PREFIX) or not backup.is_file():
        raise InputError(backup, f"not a backup of {scene_dir / ORIGINAL_FILE} (list the backups again)")
    data = backup.read_bytes()
    check_scene_gt(readers.read_json(backup), backup)
    original = scene_dir / ORIGINAL_FILE
    kept = _backup(original) if original.exists() else None
    write_file(original, data)
    return original, kept


def load_labels(dataset: Path, scene_id: int, im_id: int, T_cam_world: np.ndarray, obj_ids: list[int],
                path: Path | None = None, split: str | None = None) -> list[np.ndarray | None]:
    """The labels of image ``im_id`` as saved by ``save_labels`` (default file, or ``path``) -> per entry of
    ``obj_ids`` a (4, 4) T_world_obj, or None when the file, the image or that object has no label. Instances of
    one object take that object's entries in file order (an unlabelled first instance lets the second's label move
    up). Raises InputError for a malformed file."""
    path = labels_path(dataset, scene_id, split) if path is None else Path(path)
    entries = _image_entries(path, im_id)
    T_world_cam = invert_pose(np.asarray(T_cam_world, dtype=np.float64))
    used = [False] * len(entries)
    out: list[np.ndarray | None] = []
    for obj_id in obj_ids:
        found = None
        for j, e in enumerate(entries):
            if not used[j] and isinstance(e, dict) and e.get("obj_id") == obj_id:
                if "cam_R_m2c" not in e or "cam_t_m2c" not in e:
                    raise InputError(path, f"image {im_id} object {obj_id}: needs cam_R_m2c and cam_t_m2c")
                T_cam_obj = readers.parse_pose(e["cam_R_m2c"], e["cam_t_m2c"], path, f"image {im_id} object {obj_id}")
                found, used[j] = T_world_cam @ T_cam_obj, True
                break
        out.append(found)
    return out
