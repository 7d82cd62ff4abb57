"""Saving the whole workbench state as a *session*, and continuing it later exactly where it stopped: saving,
loading, listing, and the folder's lock. What the session's JSON holds, and how older formats are read, is
``sessions/document.py``'s.

A session named NAME is two files in one folder (the app's ``sessions/``):

- ``NAME.json``: the document (``sessions.document``), which names its arrays file with its size and SHA-256.
- ``NAME.<first 16 hex digits of its SHA-256>.npz``: the particle set (``ParticleSet.arrays()``: ``hypotheses``,
  ``projected``, ``loglik``, ``status``, ``kinds``; absent before the first step) and ``best_history``, written
  with ``np.savez`` and read with ``allow_pickle=False``. (Format 2 kept ``kinds`` in the JSON, as
  ``estimator.search.kinds``; such sessions load as they ran.)

float64 round-trips exactly through both files (Python's JSON writes the shortest repr that reads back to the
same double; NaN and infinities as ``NaN``/``Infinity``, which Python's JSON reads), so an estimator restored from a
session steps bit for bit as the saved one would have, given an evaluator with the same worker count.

Safety:
- Every file is written through a temporary file in the same folder and ``os.replace``: the arrays first, the
  JSON last. The arrays file is named after its checksum, so replacing a session (``overwrite=True``) leaves the
  old one whole until its JSON is replaced; the old arrays file is deleted only then.
- Names are *refused*, never silently changed, unless they match ``NAME_PATTERN`` (letters, digits, ``._-``, no
  leading dot, at most 64 characters): "../../etc/x" raises ``InputError``. ``suggest_name`` turns any text into a
  valid name for the UI to propose.
- An existing session is replaced only with ``overwrite=True``.
- Loading only reads. A missing, corrupt, truncated or tampered file, a future ``format_version``, or a JSON whose
  contents do not fit the arrays (object count, particle count, history length) raises ``InputError`` naming the
  file and the problem.
- Dataset files that changed or vanished since the save are not an error: ``check_dataset`` lists them so that the
  caller can warn before continuing (the run then no longer reproduces the saved one).
"""
from __future__ import annotations

import hashlib
import io
import json
import re
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.evaluation import Evaluator
from workbench.geometry import check_rigid
from workbench.inference.estimator import Estimator, parse_search
from workbench.inference.search.moves.registry import MoveKind
from workbench.inference.smc.particleset import ParticleSet
from workbench.io import bop
from workbench.io.outputs import check_creatable, check_output_file, dataset_folder_of, folder_lock, write_file
from workbench.io.readers import read_json
from workbench.problem.problem import Problem, build_problem
from workbench.problem.scene import Frame
from workbench.sessions.answer import parse_answer
from workbench.sessions.document import FrameRef, SessionState, document_json, json_default, kinds_from_json, parse_file

NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
ARRAYS_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}\.[0-9a-f]{16}\.npz")
ARRAY_DTYPES = {**ParticleSet.DTYPES, "best_history": "float64"}


@dataclass(frozen=True)
class SessionInfo:
    """One row of ``list_sessions``. ``problem``: why the session cannot be loaded (None when its JSON reads
    well; the arrays are checked only by ``load_session``), in which case the other fields may be empty."""

    name: str
    path: Path
    saved_at: str = ""
    dataset: str = ""
    scene_id: int = -1
    im_id: int = -1
    iteration: int = -1
    particles: int = 0
    method: str = ""
    labelled: int = 0
    problem: str | None = None


# ----------------------------------------------------------------------------------------------------------------
# Names and files


def check_name(name: str) -> str:
    """``name`` if it is a valid session name, else InputError (names are never changed behind the user's back)."""
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise InputError(
            "session name", f"{name!r} is not a valid session name: use 1-64 letters, digits, '.', '_' or '-', "
            f"not starting with '.', '_' or '-' (for example {suggest_name(str(name))!r})",
        )
    return name


def suggest_name(text: str) -> str:
    """A valid session name made from any text: other characters become '-', leading '.', '_', '-' go."""
    name = re.sub(r"[^A-Za-z0-9._-]+", "-", text).lstrip("._-")[:64]
    return name or "session"


def session_path(directory: Path, name: str) -> Path:
    """The JSON file of session ``name`` in ``directory``."""
    return Path(directory) / f"{check_name(name)}.json"


def file_sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def problem_fingerprint(problem: Problem) -> str:
    """SHA-256 over what the particles are scored against (grid, observed and table depth, support): equal
    fingerprints mean a restored run can reproduce the saved one."""
    h = hashlib.sha256()
    for a in (np.asarray(problem.roi, dtype=np.int64), problem.render_camera.K, problem.camera.T_cam_world,
              np.asarray(problem.observed, dtype=np.float32), np.asarray(problem.background, dtype=np.float32)):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    h.update(repr(asdict(problem.table)).encode())
    return h.hexdigest()


# ----------------------------------------------------------------------------------------------------------------
# From a running workbench to a state and back


def frame_ref_for(dataset: Path, frame: Frame, problem: Problem) -> FrameRef:
    """The reference to a frame loaded from the BOP dataset ``dataset`` (as ``problem.build.load_bop_problem`` does),
    with the checksums of its depth image, scene_camera.json, models_info.json and the object meshes."""
    root = Path(dataset).resolve()
    if frame.source is None:
        raise InputError(None, "sessions need a frame loaded from a BOP dataset (this one has no source file)")
    depth = Path(frame.source).resolve()
    split_dir = depth.parents[2]  # SPLIT/<scene>/depth/<im>.png
    try:
        split = None if split_dir == root else split_dir.relative_to(root).as_posix()
    except ValueError as e:
        raise InputError(depth, f"the depth image is not inside the dataset folder {root}") from e
    densities = {m.density for m in problem.models}
    frictions = {m.friction for m in problem.models}
    if len(densities) != 1 or len(frictions) != 1:
        raise InputError(None, "sessions store one density and one friction for all objects; these models differ")
    paths = [depth, depth.parents[1] / "scene_camera.json"]
    for model in problem.models:
        if model.source is None:
            raise InputError(None, f"model {model.obj_id} has no source file to check later")
        paths += [Path(model.source).resolve(), Path(model.source).resolve().parent / "models_info.json"]
    files = {}
    for p in dict.fromkeys(paths):
        files[p.relative_to(root).as_posix() if p.is_relative_to(root) else str(p)] = file_sha256(p)
    return FrameRef(str(root), split, int(frame.scene_id), int(frame.im_id),
                    tuple(int(m.obj_id) for m in problem.models), float(densities.pop()), float(frictions.pop()),
                    files)


def session_state_from(estimator: Estimator, frame_ref: FrameRef, labels) -> SessionState:
    """The state to save. ``labels``: per object a (4, 4) T_world_obj or None, or a (K, 4, 4) array with NaN rows
    for unlabelled objects."""
    problem = estimator.problem
    if tuple(m.obj_id for m in problem.models) != frame_ref.object_ids:
        raise InputError(None, f"the estimator's objects {[m.obj_id for m in problem.models]} are not the frame's "
                               f"{list(frame_ref.object_ids)}")
    return SessionState(
        frame=frame_ref,
        T_cam_world=np.array(problem.camera.T_cam_world, dtype=np.float64),
        table=problem.table,
        problem_config=problem.config,
        estimator_config=estimator.config,
        estimator=estimator.state_dict(),
        labels=normalise_labels(labels, problem.n_objects),
        problem_sha256=problem_fingerprint(problem),
    )


def normalise_labels(labels, n_objects: int) -> list[np.ndarray | None]:
    """Labels as a list of K entries, each a (4, 4) float64 copy or None (given as None or non-finite)."""
    labels = [None] * n_objects if labels is None else list(labels)
    if len(labels) != n_objects:
        raise InputError("labels", f"{len(labels)} labels for {n_objects} objects")
    out = []
    for T in labels:
        T = None if T is None else np.array(T, dtype=np.float64)
        if T is not None and T.shape != (4, 4):
            raise InputError("labels", f"a label must be a 4x4 pose, got shape {T.shape}")
        out.append(check_rigid(T, "labels") if T is not None and np.all(np.isfinite(T)) else None)
    return out


def session_problem(state: SessionState) -> tuple[Frame, Problem]:
    """Rebuild the saved problem from the dataset, with the saved support surface and settings (the table is not
    re-estimated). Raises InputError when dataset files are missing or unreadable; call ``check_dataset`` first
    to warn about changed ones."""
    ref = state.frame
    frame = bop.load_frame(Path(ref.dataset), ref.scene_id, ref.im_id, split=ref.split,
                           object_ids=list(ref.object_ids))
    models = bop.load_models(Path(ref.dataset), sorted(set(ref.object_ids)), density=ref.density,
                             friction=ref.friction)
    camera = frame.camera.with_pose(state.T_cam_world)
    problem = build_problem(frame, [models[i] for i in frame.object_ids], camera, state.table, state.problem_config)
    return frame, problem


def check_dataset(state: SessionState, problem: Problem | None = None) -> list[str]:
    """What no longer matches the save, one line per problem (empty: all well): dataset files missing or changed,
    and, given the rebuilt ``problem``, whether it differs from the saved run's."""
    root = Path(state.frame.dataset)
    if not root.is_dir():
        return [f"{root}: dataset folder not found"]
    problems = []
    for key, digest in state.frame.files.items():
        path = root / key  # an absolute key stays absolute
        if not path.is_file():
            problems.append(f"{path}: missing")
        elif file_sha256(path) != digest:
            problems.append(f"{path}: changed since the session was saved")
    if problem is not None and problem_fingerprint(problem) != state.problem_sha256:
        problems.append("the rebuilt problem differs from the saved run's (observed depth, table or crop): "
                        "continuing will not reproduce the saved run")
    return problems


def restore_estimator(state: SessionState, problem: Problem, evaluator: Evaluator,
                      estimator_cls: type[Estimator] = Estimator) -> Estimator:
    """A new estimator over ``problem`` (e.g. from ``session_problem``) and ``evaluator`` that continues the saved
    run: stepping it gives bit for bit what the saved estimator would have given."""
    ids = tuple(m.obj_id for m in problem.models)
    if ids != state.frame.object_ids:
        raise InputError(None, f"the session is about objects {list(state.frame.object_ids)}, this problem has "
                               f"{list(ids)}")
    estimator = estimator_cls(problem, state.estimator_config, evaluator)
    estimator.load_state(state.estimator)
    return estimator


# ----------------------------------------------------------------------------------------------------------------
# Saving


def save_session(directory: Path, name: str, state: SessionState, overwrite: bool = False) -> Path:
    """Write the session ``name`` into ``directory`` (created if missing) -> its JSON file. An existing session of
    that name is replaced only with ``overwrite``; until the new JSON is in place the old session stays whole.
    Safe with several writers of one folder (two ``serve`` on one --sessions-dir): the existence check and the
    write hold the folder's lock (``io.outputs.folder_lock``), so one of two saves of a new name is refused."""
    json_path = session_path(directory, name)
    check_sessions_dir(directory)
    with folder_lock(json_path.parent):
        return _save_locked(json_path, name, state, overwrite)


def _save_locked(json_path: Path, name: str, state: SessionState, overwrite: bool) -> Path:
    old_arrays = None
    if json_path.exists():
        if not overwrite:
            raise InputError(json_path, f"a session named {name!r} exists; choose another name or overwrite it")
        old_arrays = _own_arrays_file(json_path, name)
    # The guards of every file a command writes: only a session file of ours is replaced, even when overwriting.
    check_output_file(json_path, ours=lambda p: _own_arrays_file(p, name) is not None, force=False,
                      what="a session file", flag="session name", can_force=False)
    arrays = _arrays(state)
    npz = _npz_bytes(arrays)
    digest = hashlib.sha256(npz).hexdigest()
    npz_name = f"{name}.{digest[:16]}.npz"
    document = document_json(state, arrays, {"file": npz_name, "bytes": len(npz), "sha256": digest})
    # Encode before writing anything, so that an unserialisable value leaves the folder as it was.
    text = json.dumps(document, indent=1, default=json_default) + "\n"
    write_file(json_path.parent / npz_name, npz)  # a full disk: InputError naming the file, the old session kept
    write_file(json_path, text.encode())
    if old_arrays is not None and old_arrays != npz_name:
        (json_path.parent / old_arrays).unlink(missing_ok=True)
    return json_path


def check_sessions_dir(directory: Path) -> None:
    """Sessions may be saved in ``directory``: not a file, not below one, writable, not inside a dataset's scene or
    models folder. InputError naming it otherwise (``serve`` checks its --sessions-dir so, before serving)."""
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise InputError(directory, "is a file: sessions are saved into a folder")
    inside = dataset_folder_of(directory / "x")
    if inside is not None:
        raise InputError(directory, f"lies in the dataset folder {inside}: sessions are never saved among a "
                                    "dataset's scenes or models")
    check_creatable(directory, directory, "sessions cannot be saved below it")


def _own_arrays_file(json_path: Path, name: str) -> str | None:
    """The arrays file the existing session JSON names, if it is one this module wrote for ``name`` (a hand-edited
    JSON must never make a save delete some other file)."""
    try:
        entry = read_json(json_path)["arrays"]["file"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    pattern = re.escape(name) + r"\.[0-9a-f]{16}\.npz"
    return entry if isinstance(entry, str) and re.fullmatch(pattern, entry) else None


def _arrays(state: SessionState) -> dict[str, np.ndarray]:
    est = state.estimator
    K = len(state.frame.object_ids)
    arrays = {} if est["particles"] is None else dict(est["particles"].arrays())
    history = [np.asarray(b, dtype=np.float64) for b in est["best_history"]]
    arrays["best_history"] = np.stack(history) if history else np.zeros((0, K, 4, 4))
    return arrays


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


# ----------------------------------------------------------------------------------------------------------------
# Loading


def load_session(path: Path) -> SessionState:
    """Read and check a session's JSON file and its arrays. Raises InputError naming the file at fault and what
    is wrong with it; reads only."""
    path = Path(path)
    state, arrays_entry = parse_file(path)
    arrays = _read_arrays(path, arrays_entry)
    if "kinds_in_json" in arrays_entry:
        kinds_from_json(path, arrays, arrays_entry)
    _check_arrays(path, state, arrays, arrays_entry["shapes"])
    K = len(state.frame.object_ids)
    try:
        search = parse_search(state.estimator["search"], K)
        if parse_answer(state.estimator["answer"], K) is not None and search["map"] is None:
            raise ValueError("answer: a settled answer without an estimate (search.map) to belong to")
    except ValueError as e:
        raise InputError(path, f"estimator.{e}") from e
    state.estimator["particles"] = ParticleSet.from_arrays(arrays) if "loglik" in arrays else None
    state.estimator["best_history"] = list(arrays["best_history"])
    return state


def _read_arrays(path: Path, entry: dict) -> dict[str, np.ndarray]:
    name = entry.get("file")
    if not isinstance(name, str) or not ARRAYS_PATTERN.fullmatch(name):
        raise InputError(path, f"arrays file name {name!r} is not a plain file name in the session folder")
    npz_path = path.parent / name
    if not npz_path.is_file():
        raise InputError(npz_path, f"arrays file of session {path.name} not found")
    data = npz_path.read_bytes()
    if len(data) != entry.get("bytes"):
        raise InputError(npz_path, f"truncated or changed: {len(data)} bytes, {path.name} expects {entry.get('bytes')}")
    if hashlib.sha256(data).hexdigest() != entry.get("sha256"):
        raise InputError(npz_path, f"checksum does not match the one recorded in {path.name}: the arrays were "
                                   "changed after saving or belong to another save")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, KeyError) as e:
        raise InputError(npz_path, f"unreadable arrays file ({type(e).__name__}: {e})") from e


def _check_arrays(path: Path, state: SessionState, arrays: dict[str, np.ndarray], recorded: dict) -> None:
    """The arrays must be those the JSON records and fit its contents: K objects, N particles, one best scene per
    history entry, the particle set present exactly when a step was taken."""
    K = len(state.frame.object_ids)
    est = state.estimator
    T = len(est["history"])
    if est["iteration"] != T - 1:
        raise InputError(path, f"estimator.iteration is {est['iteration']} but the history has {T} entries")
    expected = {"best_history": (T, K, 4, 4)}
    if est["iteration"] >= 0:
        loglik = arrays.get("loglik")
        N = loglik.shape[0] if loglik is not None and loglik.ndim == 1 else 0
        if N < 1:
            raise InputError(path, "the arrays file holds no particles, but the session has taken steps")
        expected.update(hypotheses=(N, K, 4, 4), projected=(N, K, 4, 4), loglik=(N,), status=(N,), kinds=(N,))
    if sorted(arrays) != sorted(expected):
        raise InputError(path, f"the arrays file holds {sorted(arrays)}, the session needs {sorted(expected)}")
    for name, shape in expected.items():
        a = arrays[name]
        if a.shape != shape or a.dtype.name != ARRAY_DTYPES[name]:
            raise InputError(path, f"array {name!r} is {a.dtype.name} {a.shape}, the session needs "
                                   f"{ARRAY_DTYPES[name]} {shape} ({K} objects, {T} iterations)")
        if recorded.get(name) != {"shape": list(a.shape), "dtype": a.dtype.name}:
            raise InputError(path, f"array {name!r} is {a.dtype.name} {a.shape}, the JSON records {recorded.get(name)}")
    for name in ("hypotheses", "best_history"):  # what the run continues from must be rigid poses
        if name in arrays:
            check_rigid(arrays[name], f"array {name!r}", path)
    if "kinds" in arrays and not np.isin(arrays["kinds"], [int(k) for k in MoveKind]).all():
        raise InputError(path, "array 'kinds' holds unknown move kinds")


# ----------------------------------------------------------------------------------------------------------------
# Listing


def list_sessions(directory: Path) -> list[SessionInfo]:
    """The sessions in ``directory``, newest first, from their JSON files only (cheap; ``load_session`` also checks
    the arrays). A session whose JSON cannot be read is listed with ``problem`` saying why."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    out = []
    for path in sorted(directory.glob("*.json")):
        name = path.name.removesuffix(".json")
        if not NAME_PATTERN.fullmatch(name):
            continue
        try:
            state, arrays_entry = parse_file(path)
        except InputError as e:
            out.append(SessionInfo(name, path, problem=e.problem))
            continue
        loglik = arrays_entry["shapes"].get("loglik")
        arrays_file = str(arrays_entry.get("file"))
        if not ARRAYS_PATTERN.fullmatch(arrays_file):
            arrays_problem = f"arrays file name {arrays_file!r} is not a plain file name in the session folder"
        elif not (path.parent / arrays_file).is_file():
            arrays_problem = f"arrays file {arrays_file} missing"
        else:
            arrays_problem = None
        out.append(SessionInfo(
            name=name, path=path, saved_at=state.saved_at, dataset=state.frame.dataset,
            scene_id=state.frame.scene_id, im_id=state.frame.im_id, iteration=state.estimator["iteration"],
            particles=int(loglik["shape"][0]) if isinstance(loglik, dict) else 0,
            method=state.estimator_config.method, labelled=sum(T is not None for T in state.labels),
            problem=arrays_problem,
        ))
    return sorted(out, key=lambda s: (s.saved_at, s.name), reverse=True)
