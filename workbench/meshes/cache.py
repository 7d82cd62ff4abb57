"""Cache files that are checked when read: arrays in one ``.npz`` with a checksum of their contents.

The collision shapes (``physics.collision``) and the decimated render meshes (``render.depth``) are kept under
``$XDG_CACHE_HOME/workbench`` between runs. A file there can be damaged (a disk filled up, a run killed while
another copied it, a user's truncation): ``load`` reads it, compares the checksum written with it, and builds the
cached object from the arrays (a load test); any failure is reported as a WARNING naming the file, the file is
removed, and the caller rebuilds and writes it again (``save``: written to a temporary file, then renamed, so that
processes writing the same entry never leave half a file). numpy only.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from pathlib import Path
from typing import Callable, TypeVar

import numpy as np

log = logging.getLogger(__name__)

T = TypeVar("T")
_CHECKSUM = "_sha256"


def checksum(arrays: dict[str, np.ndarray]) -> str:
    """sha256 of every array's name, dtype, shape and bytes, in name order."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def load(path: Path, build: Callable[[dict[str, np.ndarray]], T]) -> T | None:
    """``build(arrays)`` of the cache file at ``path`` -> the cached object; None when there is no such file, or
    when it is damaged (unreadable, checksum missing or wrong, or ``build`` fails on it): then a WARNING names the
    file and the problem, and the file is removed so that the caller's rebuild replaces it."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
        stored = arrays.pop(_CHECKSUM, None)
        if stored is None:
            raise ValueError("it has no checksum (written by an older version)")
        if str(stored) != checksum(arrays):
            raise ValueError("its checksum does not match its contents")
        return build(arrays)
    except Exception as err:  # noqa: BLE001 - whatever a damaged file raises (BadZipFile, EOFError, ...): rebuild
        problem = str(err) if isinstance(err, ValueError) else f"{type(err).__name__}: {err}"
        log.warning("cache file %s is damaged (%s): rebuilding it", path, problem)
        try:
            path.rmdir() if path.is_dir() else path.unlink()  # (an empty folder in the file's place goes too)
        except OSError:
            pass
        return None


def save(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` with their checksum to ``path``, atomically. A cache that cannot be written (a full disk, a
    read-only cache folder) is not an error: the object is rebuilt next time, and a WARNING says why."""
    path = Path(path)
    arrays = {name: np.asarray(a) for name, a in arrays.items()}
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".", suffix=".npz.tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays, **{_CHECKSUM: np.array(checksum(arrays))})
        os.replace(tmp, path)
    except OSError as err:
        log.warning("could not write the cache file %s (%s): it will be rebuilt next time", path,
                    err.strerror or err)
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass
