"""A session's JSON document (``NAME.json``, beside its arrays file: ``sessions/store.py``): what it holds, its
format version, writing it, reading it back with every value checked, and the migrations that bring an older format
up to this one so that an old session loads and continues as it ran.

The document is versioned (``format_version``) and readable: the frame (dataset folder, split, scene and image ids,
objects, and the SHA-256 of every dataset file the problem was built from), the support surface the run used
(``T_cam_world`` and the table, so that loading never re-estimates them), every setting (estimator, problem, physics,
likelihood, render), the RNG state, the tempering and convergence state, the iteration history, the labels
(T_world_obj per object, or null), the settled answer of the current estimate with its posterior per object
(``estimator.answer``, ``answer_json``; null when not settled, or saved before it was kept), the workbench's position
in a sequence of frames (``sequence``, plain JSON the app reads and checks; absent outside a sequence), and the name,
size and SHA-256 of the arrays file.

Every value is read by the typed readers of ``io/readers.py``: a hand-edited value of the wrong type is reported
(``InputError`` naming the file and the entry), not passed on to fail somewhere later.
"""

from __future__ import annotations

import types
import typing
from dataclasses import asdict, dataclass, fields, is_dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.inference.config import EstimatorConfig
from workbench.inference.search.moves.registry import MoveKind, MoveMix
from workbench.inference.smc.filter import IterationReport
from workbench.io import readers as read
from workbench.problem.problem import ProblemConfig
from workbench.problem.scene import Table

FORMAT_VERSION = 9
# Settings a format lacked, with the values its sessions ran with (not today's defaults), so that a restored session
# steps as it did when saved: the physics' since format 2, the likelihood's since format 4, the estimator's since 5
# (a session with the clutter floor weighed it in from the start). Format 6 changed how the floor scores a reading an
# object claims on unclaimed clutter (``render.likelihood._over_clutter``): older sessions' scores are redone. Format 7
# added the estimator's leaning starts, which older sessions ran without. Format 8 added the physics backend (older
# sessions ran in Bullet) and the estimator's budget (they ran without). Format 9 added the estimator's floor_calm:
# older sessions weighed the clutter floor in at floor_from only.
FORMAT_1_PHYSICS = {"sleep_calm": False}
FORMAT_3_LIKELIHOOD = {"clutter_floor": None}
FORMAT_4_ESTIMATOR = {"floor_from": 0.0}
FORMAT_6_ESTIMATOR = {"leaning": False}
FORMAT_7_PHYSICS = {"backend": "pybullet"}
FORMAT_7_ESTIMATOR = {"budget_s": None}
FORMAT_8_ESTIMATOR = {"floor_calm": None}
KIND = "workbench-session"


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


# ----------------------------------------------------------------------------------------------------------------
# Writing


def json_default(value):
    """``json.dumps``'s fallback for what a state holds besides plain JSON: numpy scalars and arrays as numbers and
    lists, a MoveMix as its shares."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, MoveMix):
        return value.as_dict()
    raise TypeError(f"cannot store {type(value).__name__} in a session")


def document_json(state: SessionState, arrays: dict[str, np.ndarray], arrays_entry: dict) -> dict:
    """The document of ``state`` at this format, its arrays ``arrays`` in the file ``arrays_entry`` names (whose
    ``shapes`` it fills in)."""
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
# Reading, older formats brought up to this one


def parse_file(path: Path) -> tuple[SessionState, dict]:
    """The session's JSON file -> (state without arrays, the "arrays" entry), or InputError naming ``path``."""
    document = read_document(path)
    try:
        return parse_document(document)
    except InputError as e:  # a setting's own check (e.g. PhysicsConfig) names the setting, not the file
        raise InputError(path, e.problem if e.path is None else f"{e.path}: {e.problem}") from e
    except KeyError as e:
        raise InputError(path, f"malformed session: missing entry {e}") from e
    except (TypeError, ValueError, AttributeError, IndexError, OverflowError) as e:
        raise InputError(path, f"malformed session: {e}") from e


def read_document(path: Path) -> dict:
    """The session's JSON file, parsed and brought up to FORMAT_VERSION by the migrations below (the values it lacked
    filled in with those its sessions ran with), or InputError naming it."""
    if not path.is_file():
        raise InputError(path, "session file not found")
    try:
        document = read.read_json(path)
    except InputError as e:
        raise InputError(path, f"corrupt session file, not JSON the workbench reads: {e.problem}") from e
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
        _fill_estimator_settings(document, FORMAT_6_ESTIMATOR)
    if version <= 7:
        _fill_settings(document, ("problem_config", "physics"), FORMAT_7_PHYSICS)
        _fill_estimator_settings(document, FORMAT_7_ESTIMATOR)
    if version <= 8:
        _fill_estimator_settings(document, FORMAT_8_ESTIMATOR)
    return document


def _fill_estimator_settings(document: dict, values: dict) -> None:
    """``_fill_settings`` of both estimator settings a session keeps: the run's, and its sequence's (since format
    6)."""
    for at in (("estimator_config",), ("sequence", "config")):
        _fill_settings(document, at, values)


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
    (in place) for ``kinds_from_json`` once the arrays are read."""
    search = _search_state(document)
    kinds = search.pop("kinds", None) if isinstance(search, dict) else None
    if isinstance(document.get("arrays"), dict):
        document["arrays"]["kinds_in_json"] = kinds


def kinds_from_json(path: Path, arrays: dict[str, np.ndarray], entry: dict) -> None:
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


def parse_document(d: dict) -> tuple[SessionState, dict]:
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
        if typing.get_origin(tp) is types.UnionType and type(None) in typing.get_args(tp):  # e.g. float | None
            if v is None:
                kwargs[name] = None
                continue
            tp = next(a for a in typing.get_args(tp) if a is not type(None))
        if is_dataclass(tp):
            kwargs[name] = config_from_dict(tp, v, at)
        elif tp is float:
            kwargs[name] = read.number(v, at)
        elif tp is int:
            kwargs[name] = read.integer(v, at)
        elif tp is str:
            kwargs[name] = read.string(v, at)
        elif typing.get_origin(tp) is typing.Literal:  # e.g. PhysicsConfig.backend: one of its choices
            kwargs[name] = read.string(v, at)
            if kwargs[name] not in typing.get_args(tp):
                raise ValueError(f"{at} must be one of {', '.join(typing.get_args(tp))}, got {v!r}")
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
