"""Saving the whole workbench state as a *session*, and continuing it later exactly where it stopped.

A session named NAME is two files in one folder (the app's ``sessions/``):

- ``NAME.json``: versioned (``format_version``) and readable: the frame (dataset folder, split, scene and image
  ids, objects, and the SHA-256 of every dataset file the problem was built from), the support surface the run
  used (``T_cam_world`` and the table, so that loading never re-estimates them), every setting (estimator,
  problem, physics, likelihood, render), the RNG state, the tempering and convergence state, the iteration
  history, the labels (T_world_obj per object, or null), the settled answer of the current estimate with its
  posterior per object (``estimator.answer``, ``answer_json``; null when not settled, or saved before it was
  kept), the workbench's position in a sequence of frames (``sequence``, plain JSON the app reads and checks;
  absent outside a sequence), and the name, size and SHA-256 of the arrays file.
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
import typing
import zipfile
from dataclasses import asdict, dataclass, fields, is_dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.evaluation import Evaluator
from workbench.geometry import check_rigid
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator, parse_search
from workbench.inference.search.moves.registry import MoveKind, MoveMix
from workbench.inference.smc.filter import IterationReport
from workbench.inference.smc.particleset import ParticleSet
from workbench.io import bop
from workbench.io import readers as read
from workbench.io.outputs import check_creatable, check_output_file, dataset_folder_of, folder_lock, write_file
from workbench.problem.problem import Problem, ProblemConfig, build_problem
from workbench.problem.scene import Frame, Table
from workbench.sessions.answer import parse_answer

FORMAT_VERSION = 7
# Settings a format lacked, with the values its sessions ran with (not today's defaults), so that a restored session
# steps as it did when saved: the physics' since format 2, the likelihood's since format 4, the estimator's since 5
# (a session with the clutter floor weighed it in from the start). Format 6 changed how the floor scores a reading an
# object claims on unclaimed clutter (``render.likelihood._over_clutter``): older sessions' scores are redone. Format 7
# added the estimator's leaning starts, which older sessions ran without.
FORMAT_1_PHYSICS = {"sleep_calm": False}
FORMAT_3_LIKELIHOOD = {"clutter_floor": None}
FORMAT_4_ESTIMATOR = {"floor_from": 0.0}
FORMAT_6_ESTIMATOR = {"leaning": False}
KIND = "workbench-session"
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
ARRAYS_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}\.[0-9a-f]{16}\.npz")
ARRAY_DTYPES = {**ParticleSet.DTYPES, "best_history": "float64"}


@dataclass(frozen=True)
class FrameRef:
    """Which frame of which BOP dataset a session is about. ``dataset``: absolute folder; ``split``: the split
    folder below it (None when ``dataset`` is the split folder); ``files``: SHA-256 (hex) of every file the
    problem was built from, keyed by path relative to ``dataset`` (absolute when outside it)."""

    dataset: str
    split: str | None
    scene_id: int
    im_id: int
    object_ids: tuple[int, ...]
    density: float
    friction: float
    files: dict[str, str]


@dataclass
class SessionState:
    """Everything a session holds. ``estimator``: ``Estimator.state_dict()``; ``labels``: per object a (4, 4)
    T_world_obj or None; ``problem_sha256``: ``problem_fingerprint`` of the problem the run used; ``sequence``: the
    workbench's position in the frame's sequence (``sessions.sequence_record``), stored as given, or None."""

    frame: FrameRef
    T_cam_world: np.ndarray
    table: Table
    problem_config: ProblemConfig
    estimator_config: EstimatorConfig
    estimator: dict
    labels: list[np.ndarray | None]
    problem_sha256: str
    saved_at: str = ""
    sequence: dict | None = None


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
    document = _document(state, arrays, {"file": npz_name, "bytes": len(npz), "sha256": digest})
    # Encode before writing anything, so that an unserialisable value leaves the folder as it was.
    text = json.dumps(document, indent=1, default=_json_default) + "\n"
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
        entry = json.loads(json_path.read_text())["arrays"]["file"]
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


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, MoveMix):
        return value.as_dict()
    raise TypeError(f"cannot store {type(value).__name__} in a session")


def _document(state: SessionState, arrays: dict[str, np.ndarray], arrays_entry: dict) -> dict:
    est = state.estimator
    arrays_entry["shapes"] = {k: {"shape": list(a.shape), "dtype": a.dtype.name} for k, a in arrays.items()}
    return {
        "format_version": FORMAT_VERSION,
        "kind": KIND,
        "saved_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "frame": {**asdict(state.frame), "object_ids": list(state.frame.object_ids)},
        "support": {"T_cam_world": np.asarray(state.T_cam_world, dtype=np.float64).tolist(),
                    "table": asdict(state.table)},
        "problem_sha256": state.problem_sha256,
        "problem_config": asdict(state.problem_config),
        "estimator_config": asdict(state.estimator_config),
        "estimator": {
            "iteration": est["iteration"],
            "rng": est["rng"],
            "beta": est["beta"],
            "calm": est["calm"],
            "history": [r.as_dict() for r in est["history"]],
            "search": est.get("search"),
            "answer": est.get("answer"),
        },
        "labels": [None if T is None else np.asarray(T, dtype=np.float64).tolist() for T in state.labels],
        "arrays": arrays_entry,
        **({} if state.sequence is None else {"sequence": state.sequence}),
    }


# ----------------------------------------------------------------------------------------------------------------
# Loading


def load_session(path: Path) -> SessionState:
    """Read and check a session's JSON file and its arrays. Raises InputError naming the file at fault and what
    is wrong with it; reads only."""
    path = Path(path)
    state, arrays_entry = _parse(path)
    arrays = _read_arrays(path, arrays_entry)
    if "kinds_in_json" in arrays_entry:
        _kinds_from_json(path, arrays, arrays_entry)
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


def _parse(path: Path) -> tuple[SessionState, dict]:
    """The session's JSON file -> (state without arrays, the "arrays" entry), or InputError naming ``path``."""
    document = _read_document(path)
    try:
        return _parse_document(document)
    except InputError as e:  # a setting's own check (e.g. PhysicsConfig) names the setting, not the file
        raise InputError(path, e.problem if e.path is None else f"{e.path}: {e.problem}") from e
    except KeyError as e:
        raise InputError(path, f"malformed session: missing entry {e}") from e
    except (TypeError, ValueError, AttributeError, IndexError, OverflowError) as e:
        raise InputError(path, f"malformed session: {e}") from e


def _read_document(path: Path) -> dict:
    if not path.is_file():
        raise InputError(path, "session file not found")
    try:
        document = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"corrupt session file, not JSON ({e})") from e
    if not isinstance(document, dict) or document.get("kind") != KIND:
        raise InputError(path, "not a workbench session file")
    version = document.get("format_version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise InputError(path, f"invalid format_version {version!r}")
    if version > FORMAT_VERSION:
        raise InputError(path, f"written by a newer workbench (session format {version}; this one reads up to "
                               f"{FORMAT_VERSION}): update the workbench to open it")
    if version == 1:
        _fill_settings(document, ("problem_config", "physics"), FORMAT_1_PHYSICS)
    if version <= 2:
        _upgrade_format_2(document)
    if version <= 3:
        _fill_settings(document, ("problem_config", "likelihood"), FORMAT_3_LIKELIHOOD)
    if version <= 4:
        _fill_settings(document, ("estimator_config",), FORMAT_4_ESTIMATOR)
    if version <= 5:
        _rescore_floor(document)
    if version <= 6:
        for at in (("estimator_config",), ("sequence", "config")):
            _fill_settings(document, at, FORMAT_6_ESTIMATOR)
    return document


def _fill_settings(document: dict, path: tuple[str, ...], values: dict) -> None:
    """Fill in the settings at ``path`` (e.g. ``problem_config.physics``) that an older format lacked with
    ``values``, the ones its sessions ran with (in place); a malformed document is left for ``config_from_dict`` to
    report."""
    settings = document
    for name in path:
        settings = settings.get(name) if isinstance(settings, dict) else None
    if isinstance(settings, dict):
        for name, value in values.items():
            settings.setdefault(name, value)


def _search_state(document: dict):
    """The document's ``estimator.search`` entry as it stands (None where a level is missing or not a dict), for the
    format upgrades; a malformed one is left for ``parse_search`` to report."""
    estimator = document.get("estimator")
    return estimator.get("search") if isinstance(estimator, dict) else None


def _rescore_floor(document: dict) -> None:
    """Sessions before format 6 scored the clutter floor by an older rule: their search state is marked as not yet
    weighing the floor in (in place), so the next step scores the particles and the estimate again
    (``ParticleFilter.weigh_floor_in``) instead of ranking them against hypotheses scored by today's rule."""
    search = _search_state(document)
    if isinstance(search, dict):
        search["floor_in"] = False


def _upgrade_format_2(document: dict) -> None:
    """Format 2 kept each particle's move kind in the JSON (``estimator.search.kinds``, absent before the search
    existed); format 3 keeps it in the arrays file with the rest of the particle set. Noted in the "arrays" entry
    (in place) for ``_kinds_from_json`` once the arrays are read."""
    search = _search_state(document)
    kinds = search.pop("kinds", None) if isinstance(search, dict) else None
    if isinstance(document.get("arrays"), dict):
        document["arrays"]["kinds_in_json"] = kinds


def _kinds_from_json(path: Path, arrays: dict[str, np.ndarray], entry: dict) -> None:
    """A format-2 session's move kinds (``entry["kinds_in_json"]``, or START for every particle where it had none)
    added to its ``arrays`` (in place), recorded as format 3 records them."""
    loglik = arrays.get("loglik")
    if loglik is None or loglik.ndim != 1:
        return  # no particles (or malformed ones, which _check_arrays reports)
    kinds = entry["kinds_in_json"]
    if kinds is None:
        kinds = np.full(len(loglik), int(MoveKind.START), np.int8)
    elif not (isinstance(kinds, list) and all(isinstance(k, int) and not isinstance(k, bool) for k in kinds)):
        raise InputError(path, "estimator.search.kinds must be a list of integers")
    arrays["kinds"] = np.asarray(kinds, dtype=np.int64).astype(np.int8) if len(kinds) else np.zeros(0, np.int8)
    if len(kinds) and not np.array_equal(arrays["kinds"], np.asarray(kinds)):
        raise InputError(path, "estimator.search.kinds holds unknown move kinds")
    entry["shapes"]["kinds"] = {"shape": list(arrays["kinds"].shape), "dtype": "int8"}


def _parse_document(d: dict) -> tuple[SessionState, dict]:
    f = d["frame"]
    files = f["files"]
    if not (isinstance(files, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in files.items())):
        raise ValueError("frame.files must map file names to checksums")
    object_ids = tuple(read.integer(i, "frame.object_ids") for i in f["object_ids"])
    if not object_ids:
        raise ValueError("frame.object_ids is empty")
    split = None if f["split"] is None else read.string(f["split"], "frame.split")
    frame = FrameRef(read.string(f["dataset"], "frame.dataset"), split,
                     read.integer(f["scene_id"], "frame.scene_id"), read.integer(f["im_id"], "frame.im_id"),
                     object_ids, read.number(f["density"], "frame.density"),
                     read.number(f["friction"], "frame.friction"), dict(files))
    T_cam_world = read.pose(d["support"]["T_cam_world"], "support.T_cam_world")
    if np.abs(T_cam_world[:3, 3]).max() > read.MAX_TABLE_DISTANCE:
        raise ValueError(f"support.T_cam_world puts the table more than {read.MAX_TABLE_DISTANCE:g} m from the "
                         "camera")
    t = d["support"]["table"]
    table = Table(*(read.number(t[k], f"table.{k}") for k in ("x_min", "x_max", "y_min", "y_max")),
                  region_min=read.pair(t["region_min"], "table.region_min"),
                  region_max=read.pair(t["region_max"], "table.region_max"))
    _check_table(table)
    problem_config = config_from_dict(ProblemConfig, d["problem_config"], "problem_config")
    problem_config.validate("problem_config.")
    estimator_config = config_from_dict(EstimatorConfig, d["estimator_config"], "estimator_config")
    estimator_config.validate("estimator_config.")  # the command line's bounds, seed included
    e = d["estimator"]
    beta = read.number(e["beta"], "estimator.beta")
    if not 0.0 < beta <= 1.0:  # the tempering exponent temper_to_ess chooses
        raise ValueError(f"estimator.beta must lie in (0, 1], got {beta!r}")
    if read.integer(e["calm"], "estimator.calm") < 0:
        raise ValueError(f"estimator.calm must be >= 0, got {e['calm']!r}")
    labels = d["labels"]
    if not isinstance(labels, list) or len(labels) != len(object_ids):
        raise ValueError(f"labels must list one pose or null for each of the {len(object_ids)} objects")
    state = SessionState(
        frame=frame,
        T_cam_world=T_cam_world,
        table=table,
        problem_config=problem_config,
        estimator_config=estimator_config,
        estimator={
            "iteration": read.integer(e["iteration"], "estimator.iteration"),
            "rng": _rng_state(e["rng"]),
            "beta": beta,
            "calm": read.integer(e["calm"], "estimator.calm"),
            "history": [_report(r) for r in e["history"]],
            "search": _search(e.get("search")),
            "answer": e.get("answer"),  # checked with the search, once the arrays are read
        },
        labels=[None if T is None else read.pose(T, "labels") for T in labels],
        problem_sha256=read.string(d["problem_sha256"], "problem_sha256"),
        saved_at=read.string(d["saved_at"], "saved_at"),
    )
    state.sequence = d.get("sequence")
    if not isinstance(state.sequence, (dict, type(None))):
        raise ValueError("sequence must be an object")
    arrays_entry = d["arrays"]
    if not isinstance(arrays_entry["shapes"], dict):
        raise ValueError("arrays.shapes must be an object")
    return state, arrays_entry


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


def _check_table(table: Table) -> None:
    """A table within reach of the camera, its object region inside it (the estimator draws particles there)."""
    lo = (table.x_min, table.y_min, *table.region_min)
    hi = (table.x_max, table.y_max, *table.region_max)
    if not all(np.isfinite(v) and abs(v) <= read.MAX_TABLE_DISTANCE for v in lo + hi):
        raise ValueError(f"support.table values must be finite and within {read.MAX_TABLE_DISTANCE:g} m")
    if not (table.x_min < table.x_max and table.y_min < table.y_max
            and all(a <= b for a, b in zip(table.region_min, table.region_max))):
        raise ValueError("support.table: each minimum must lie below its maximum")


def _rng_state(v) -> dict:
    try:
        np.random.default_rng().bit_generator.state = v  # the estimator's generator kind, numpy's own check
    except (TypeError, ValueError, KeyError, OverflowError) as e:
        raise ValueError(f"estimator.rng is not a valid PCG64 state ({e})") from e
    return v


def _search(v) -> dict | None:
    """The estimator's search state (estimate, move kinds, candidates): plain JSON, shapes checked on load."""
    if v is not None and not isinstance(v, dict):
        raise ValueError("estimator.search must be an object")
    return v


def _report(v) -> IterationReport:
    names = [f.name for f in fields(IterationReport)]
    if isinstance(v, dict) and "sink_m" not in v:  # saved before the sink was fitted: objects on the plane
        v = {**v, "sink_m": 0.0}
    if not isinstance(v, dict) or sorted(v) != sorted(names):
        raise ValueError(f"a history entry must have exactly the fields {names}")
    if not isinstance(v["timings"], dict):
        raise ValueError("history timings must be an object")
    values = {k: read.number(v[k], f"history.{k}") for k in names if k not in ("iteration", "converged", "n_failed",
                                                                            "timings", "moves", "best_kind")}
    moves = v["moves"]
    if not (isinstance(moves, dict) and all(isinstance(c, dict) for c in moves.values())):
        raise ValueError("history.moves must map move kinds to counts")
    if not isinstance(v["converged"], bool):
        raise ValueError("history.converged must be true or false")
    return IterationReport(iteration=read.integer(v["iteration"], "history.iteration"), converged=v["converged"],
                           n_failed=read.integer(v["n_failed"], "history.n_failed"),
                           timings={str(k): read.number(t, "history.timings") for k, t in v["timings"].items()},
                           moves={str(k): {str(n): read.number(x, "history.moves") for n, x in c.items()}
                                  for k, c in moves.items()},
                           best_kind=read.string(v["best_kind"], "history.best_kind"), **values)


def config_from_dict(cls, data, where: str):
    """Rebuild a (nested) settings dataclass from ``asdict`` output, checking every field's type; all fields must
    be present and no others (a session must not silently fall back to today's defaults)."""
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be an object")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in fields(cls)]
    if sorted(data) != sorted(names):
        missing, extra = sorted(set(names) - set(data)), sorted(set(data) - set(names))
        raise ValueError(f"{where}: missing settings {missing}, unknown settings {extra}")
    kwargs = {}
    for name in names:
        tp, v, at = hints[name], data[name], f"{where}.{name}"
        if is_dataclass(tp):
            kwargs[name] = config_from_dict(tp, v, at)
        elif tp is float:
            kwargs[name] = read.number(v, at)
        elif tp == float | None:
            kwargs[name] = None if v is None else read.number(v, at)
        elif tp is int:
            kwargs[name] = read.integer(v, at)
        elif tp is str:
            kwargs[name] = read.string(v, at)
        elif tp is bool:
            kwargs[name] = read.boolean(v, at)
        elif tp is MoveMix:  # kind -> share; a kind added since the save gets 0, as the session ran without it
            if not isinstance(v, dict):
                raise ValueError(f"{at} must map move kinds to shares, got {v!r}")
            kwargs[name] = MoveMix.from_dict({str(k): read.number(x, f"{at}.{k}") for k, x in v.items()})
        elif tp == tuple[tuple[int, str], ...]:  # e.g. PhysicsConfig.shape_overrides: (obj_id, kind) pairs
            if not isinstance(v, list) or not all(isinstance(p, list) and len(p) == 2 for p in v):
                raise ValueError(f"{at} must be a list of [integer, string] pairs, got {v!r}")
            kwargs[name] = tuple((read.integer(a, at), read.string(b, at)) for a, b in v)
        else:
            raise ValueError(f"{at}: settings of type {tp} cannot be restored")
    return cls(**kwargs)


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
            state, arrays_entry = _parse(path)
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
