"""Typed readers of JSON values, one set for every file the workbench reads: JSON that parses may still hold a
string where a number belongs, or a reflection where a pose belongs, and each reader names where and what was
expected, so that a hand-edited or corrupt value is reported, never passed on to fail somewhere later.

Two families, by who names the file:
- ``read_json`` and the ``expect_*`` / ``parse_*`` readers of a dataset's files (``io.bop``, ``io.plainframe``,
  ``score``, ``track``) raise ``InputError(path, ...)`` naming the file and the key;
- the entry readers of a session (``sessions.document``, ``sessions.answer``, ``inference.estimator.parse_search``)
  raise ``ValueError`` naming the entry ("estimator.beta must be a number ..."), which the session loader turns into
  an ``InputError`` naming the session file.
Their messages differ where the files' users read different words; each reader keeps its own.
"""

from __future__ import annotations

import hashlib
import json
import threading
from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.geometry import check_rigid, make_pose

MM = 1e-3  # metres per millimetre: BOP's files give translations in millimetres
MAX_TABLE_DISTANCE = 100.0  # metres from the camera to the table frame's origin (along any axis)


# ----------------------------------------------------------------------------------------------------------------
# A dataset's files: InputError naming the file


# Limits of every JSON file read (``read_json``, ``parse_json``): a hand-edited or hostile file is refused by name
# before it can exhaust the stack, the memory or Python's integer parser.
MAX_JSON_BYTES = 128 * 2**20  # the largest BOP file (a scene_gt_info.json of 1000 images) is ~10 MB; parsing takes
#                               ~10x the file's size in memory
MAX_JSON_DEPTH = 64  # a BOP file nests 3 levels, a session 8; Python's own parser fails near 1000 levels
MAX_NUMBER_CHARS = 100  # a float64 needs 24 characters, numpy's 128-bit RNG state 39 digits; a 400-digit integer
#                         overflows a float, and 4300 digits are beyond what Python parses


def read_json(path: Path) -> dict | list:
    """The parsed JSON file, within the limits above, or InputError naming it."""
    path = Path(path)
    return parse_json(_read_bytes(path), path)


def _read_bytes(path: Path) -> bytes:
    """The file's bytes, at most MAX_JSON_BYTES of them, or InputError naming it."""
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        size = path.stat().st_size
        if size > MAX_JSON_BYTES:
            raise InputError(path, f"is {size / 2**20:.0f} MB, more than any input of the workbench "
                                   f"({MAX_JSON_BYTES // 2**20} MB): not the file meant?")
        return path.read_bytes()
    except OSError as e:
        raise InputError(path, f"cannot be read ({e.strerror or e})") from e


# Files ``read_json_kept`` holds, newest last: a scene's camera and truth and its models' info, which every frame
# reads, and one more. Few: a 2000-image scene's scene_gt.json (3.4 MB) parsed holds ~9 MB.
KEPT_FILES = 4
_KEPT: dict[tuple, dict | list] = {}
_KEPT_LOCK = threading.Lock()  # the server's threads may read frames side by side


def read_json_kept(path: Path) -> dict | list:
    """``read_json(path)``, parsed once while the file's bytes stay the same (known by their hash: reading and
    hashing a file is a small part of parsing it, and a hash is not fooled by a file rewritten within the
    timestamps' granularity). For a sequence's per-image files, which every frame reads: a 2000-image scene's
    scene_gt.json takes ~0.1 s to parse, a third of a tracked frame. The value is shared between callers: read it,
    never change it."""
    path = Path(path)
    data = _read_bytes(path)
    key = (str(path.resolve()), hashlib.blake2b(data, digest_size=16).digest())
    with _KEPT_LOCK:
        value = _KEPT.pop(key, None)
    if value is None:
        value = parse_json(data, path)
    with _KEPT_LOCK:
        while len(_KEPT) >= KEPT_FILES:
            _KEPT.pop(next(iter(_KEPT)))
        _KEPT[key] = value  # newest last
    return value


def parse_json(data: bytes | str, path: Path | str) -> dict | list:
    """``data`` (UTF-8) parsed, within the limits above, or InputError naming ``path``: corrupt JSON, nesting deeper
    than MAX_JSON_DEPTH, or a number longer than MAX_NUMBER_CHARS."""
    if len(data) > MAX_JSON_BYTES:
        raise InputError(path, f"holds {len(data) / 2**20:.0f} MB, more than any input of the workbench "
                               f"({MAX_JSON_BYTES // 2**20} MB)")
    try:
        text = data.decode("utf-8") if isinstance(data, bytes) else data
        value = json.loads(text, parse_int=_bounded(int), parse_float=_bounded(float))
    except _LongNumber as e:
        raise InputError(path, f"holds a number of {e.args[0]} characters ({e.args[1]}...); no value the "
                               f"workbench reads needs more than {MAX_NUMBER_CHARS}") from None
    except RecursionError:
        raise InputError(path, f"is nested deeper than Python can read; no input of the workbench nests more than "
                               f"{MAX_JSON_DEPTH} levels") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(path, f"corrupt JSON ({e}); re-export or re-download the file") from e
    if _nesting_exceeds(value, MAX_JSON_DEPTH):
        raise InputError(path, f"is nested more than {MAX_JSON_DEPTH} levels deep; no input of the workbench is")
    return value


class _LongNumber(Exception):
    """A JSON number literal longer than MAX_NUMBER_CHARS: (its length, its start)."""


def _bounded(convert):
    """``convert`` for a JSON number literal, refusing one longer than MAX_NUMBER_CHARS before converting it."""
    def parse(literal: str):
        if len(literal) > MAX_NUMBER_CHARS:
            raise _LongNumber(len(literal), literal[:20])
        return convert(literal)
    return parse


def _nesting_exceeds(value, limit: int) -> bool:
    """Whether lists and objects in ``value`` nest more than ``limit`` levels (walked without recursion)."""
    stack = [(value, 1)]
    while stack:
        item, level = stack.pop()
        children = item.values() if isinstance(item, dict) else item if isinstance(item, list) else ()
        for child in children:
            if isinstance(child, (dict, list)):
                if level + 1 > limit:
                    return True
                stack.append((child, level + 1))
    return False


def expect_object(value, path: Path, what: str) -> dict:
    if not isinstance(value, dict):
        raise InputError(path, f"{what} must be a JSON object {{...}}, got {json_kind(value)}")
    return value


def expect_list(value, path: Path, what: str) -> list:
    if not isinstance(value, list):
        raise InputError(path, f"{what} must be a JSON list [...], got {json_kind(value)}")
    return value


def expect_int(value, path: Path, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise InputError(path, f"{what} must be a whole number, got {json_kind(value)}")
    return value


def expect_number(value, path: Path, what: str) -> float:
    """A finite JSON number -> float."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(path, f"{what} must be a number, got {json_kind(value)}")
    try:
        number = float(value)
    except OverflowError:  # an integer beyond float range
        number = float("inf")
    if not np.isfinite(number):
        raise InputError(path, f"{what} must be a finite number, got {value!r:.40}")
    return number


def json_kind(value) -> str:
    """A JSON value for an error message: its type and the start of its text."""
    names = {dict: "an object", list: "a list", str: "a string", bool: "a boolean", int: "a number",
             float: "a number", type(None): "null"}
    return f"{names.get(type(value), type(value).__name__)} {json.dumps(value)[:40]}"


def parse_pose(R, t, path: Path, what: str, t_unit: float = MM) -> np.ndarray:
    """Rotation (9 numbers row-major) and translation (3 numbers, in units of ``t_unit`` metres) -> (4, 4) metres.

    The rotation is re-orthonormalised: JSON files store it with a few digits only."""
    try:
        R = np.asarray(R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(t, dtype=np.float64).reshape(3)
    except (TypeError, ValueError) as e:
        raise InputError(path, f"{what}: rotation must be 9 numbers and translation 3 numbers") from e
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise InputError(path, f"{what} contains NaN or inf")
    # Entries of a rotation lie in [-1, 1]: checked first so that huge values are refused without overflowing.
    if np.abs(R).max() > 1.001 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise InputError(path, f"{what}: the rotation is not orthonormal with determinant +1 ({R.ravel().tolist()})")
    U, _, Vt = np.linalg.svd(R)
    return make_pose(U @ Vt, t * t_unit)


def parse_T(values, path: Path, what: str, t_unit: float = 1.0) -> np.ndarray:
    """A 4x4 rigid pose (nested list or 16 numbers, translation in units of ``t_unit`` metres) -> (4, 4) metres."""
    try:
        T = np.asarray(values, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError) as e:
        raise InputError(path, f"{what} must be a 4x4 matrix") from e
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(path, f"{what}: last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    return parse_pose(T[:3, :3], T[:3, 3], path, what, t_unit)


# ----------------------------------------------------------------------------------------------------------------
# A session's entries: ValueError naming the entry


def integer(v, where: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"{where} must be an integer, got {v!r}")
    return v


def number(v, where: str) -> float:
    """Any JSON number as float, NaN and infinities too (Python's JSON writes them: a log-likelihood may be -inf)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"{where} must be a number, got {v!r}")
    return float(v)


def string(v, where: str) -> str:
    if not isinstance(v, str):
        raise ValueError(f"{where} must be a string, got {v!r}")
    return v


def boolean(v, where: str) -> bool:
    if not isinstance(v, bool):
        raise ValueError(f"{where} must be true or false, got {v!r}")
    return v


def pair(v, where: str) -> tuple[float, float]:
    if not isinstance(v, list) or len(v) != 2:
        raise ValueError(f"{where} must be two numbers")
    return (number(v[0], where), number(v[1], where))


def exact_keys(value, keys: tuple[str, ...], where: str) -> None:
    if not isinstance(value, dict):
        raise ValueError(f"{where} must be an object")
    if sorted(value) != sorted(keys):
        raise ValueError(f"{where} must have exactly the entries {list(keys)}, got {sorted(value)}")


def json_list(value, where: str) -> list:
    if not isinstance(value, list):
        raise ValueError(f"{where} must be a list")
    return value


def short_text(value, where: str) -> str:
    if not isinstance(value, str) or len(value) > 200:
        raise ValueError(f"{where} must be a short text")
    return value


def quantity(value, where: str, finite: bool = True) -> float:
    """A number that is not NaN, and finite unless ``finite`` is False."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or np.isnan(value) \
            or (finite and not np.isfinite(value)):
        raise ValueError(f"{where} must be a {'finite ' if finite else ''}number, got {value!r}")
    return float(value)


def finite_array(value, shape: tuple, dtype, where: str) -> np.ndarray:
    """Finite numbers of ``shape`` as an array of ``dtype``. A value numpy cannot convert raises numpy's own error."""
    a = np.asarray(value, dtype=dtype)
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise ValueError(f"{where} must be finite numbers of shape {shape}, got shape {a.shape}")
    return a


def rigid(T: np.ndarray, where: str) -> np.ndarray:
    """``geometry.check_rigid`` for an entry: its problem as a ValueError (the loader names the file)."""
    try:
        return check_rigid(T, where)
    except InputError as e:
        raise ValueError(e.problem) from e


def pose(v, where: str) -> np.ndarray:
    """A rigid 4x4 pose (a reflection or a bad bottom row is refused, not turned into another pose)."""
    try:
        T = np.array(v, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as e:
        raise ValueError(f"{where} must be a finite 4x4 matrix") from e
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{where} must be a finite 4x4 matrix")
    return rigid(T, where)


def poses(value, shape: tuple, where: str) -> np.ndarray:
    """Rigid poses of ``shape`` (a reflection or a bad bottom row is refused)."""
    try:
        T = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as e:
        raise ValueError(f"{where} must be finite numbers of shape {shape}") from e
    return rigid(finite_array(T, shape, np.float64, where), where)


def table_poses(value, shape: tuple, where: str) -> np.ndarray:
    """Scene poses of the given ``shape`` (..., 4, 4), table frame, m: rigid, and within MAX_TABLE_DISTANCE of the
    table's origin. A corrupt session's pose 1e308 m away would otherwise overflow the search's distances."""
    a = rigid(finite_array(value, shape, np.float64, where), where)
    if np.abs(a[..., :3, 3]).max(initial=0.0) > MAX_TABLE_DISTANCE:
        raise ValueError(f"{where}: a position lies more than {MAX_TABLE_DISTANCE:g} m from the table")
    return a
