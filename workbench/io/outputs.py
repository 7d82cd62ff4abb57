"""Where a command may write, the same rules for every file any command writes (``estimate --out``, ``score
--json``, ``bench --out``, sessions): checked before any work, written whole or not at all, and one run at a time.

- ``check_output_file``: refuses a folder, a path below a file, a place without write permission, something that
  is not a regular file (``/dev/full``, a pipe), anything inside a dataset's scene or models folder, any file of a
  dataset's own (``camera.json``, ``models_info.json``, ...) even with ``--force``, and an existing file that is not
  one of ours unless ``--force``.
- ``write_file``: writes through a temporary file renamed into place (so a full disk or a kill leaves the old file
  whole), through a symbolic link to its target (the link stays a link), keeping a replaced file's permissions; a
  write that fails is an ``InputError`` naming the file.
- ``check_distinct``: the files of one command (``--out``, ``--posterior``, ``--json``, ...) are different files.
- ``OutputLock``: an advisory lock (``flock``) beside the file, held for the whole run: a second run writing the
  same file is refused at once, naming the first run's pid. The kernel drops the lock when its process dies.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

from workbench.errors import InputError

# Files that make a folder a BOP dataset's (its root, a split, a scene or the models folder): never replaced.
DATASET_MARKERS = ("scene_camera.json", "scene_gt.json", "models_info.json")


def dataset_folder_of(path: Path) -> Path | None:
    """The scene or models folder of a BOP dataset that ``path`` (resolved) lies in, if any: a folder holding
    scene_camera.json or models_info.json, or a depth/rgb/mask folder below one."""
    for folder in Path(path).resolve().parents:
        if (folder / "scene_camera.json").is_file() or (folder / "models_info.json").is_file():
            return folder
    return None


def dataset_root_of(path: Path) -> Path | None:
    """The BOP dataset whose root ``path`` (resolved) lies in, at any depth: a folder with ``models/
    models_info.json`` (or ``models_*/``)."""
    for folder in Path(path).resolve().parents:
        if (folder / "models" / "models_info.json").is_file() or any(
                (m / "models_info.json").is_file() for m in folder.glob("models_*")):
            return folder
    return None


def is_datasets_own_file(path: Path) -> bool:
    """``path`` is a file of a dataset: one of its marker files anywhere, or any file beside its models folder
    (camera.json, scenes.json, README.md, ...)."""
    target = Path(path).resolve()
    if target.name in DATASET_MARKERS:
        return True
    root = dataset_root_of(target)
    return root is not None and target.parent == root


def check_output_file(path: Path, ours: Callable[[Path], bool] | None = None, force: bool = False,
                      what: str = "the output", flag: str = "--out", can_force: bool = True) -> bool:
    """Check, before any work, that a command may write the file ``path`` -> whether it exists (and is ours, or
    ``force``). InputError naming ``path``, and nothing written, when it may not: see the module doc. ``ours(p)``
    says whether an existing file is one this command wrote (default: none is)."""
    path = Path(path)
    target = path.resolve()
    inside = dataset_folder_of(target)
    if inside is not None:
        raise InputError(path, f"lies in the dataset folder {inside}: {what} is never written among a dataset's "
                               f"scenes or models; choose a {flag} outside them")
    if target.is_dir():
        raise InputError(path, f"is a folder: {flag} names a file")
    check_creatable(path, target.parent, "nothing can be written below it")
    if not target.exists():
        return False
    if not stat.S_ISREG(target.stat().st_mode):
        raise InputError(path, f"is not a regular file (a device, a pipe, ...): choose another {flag}")
    if not os.access(target, os.W_OK):
        raise InputError(path, "no permission to replace this file")
    mine = ours is not None and _safely(ours, target)
    if not mine and is_datasets_own_file(target):
        raise InputError(path, f"is a file of the dataset {dataset_root_of(target) or target.parent}: it is never "
                               f"replaced, not even with --force; choose another {flag}")
    if not mine and not force:
        raise InputError(path, f"exists and is not {what}; it was left as it is. Choose another {flag}"
                               + (", or pass --force to replace it" if can_force else ", or move the file away"))
    return True


def check_distinct(paths: dict[str, Path | None]) -> None:
    """The files one command writes or reads, by flag (``{"--out": ..., "--posterior": ...}``; None for a flag not
    given), are all different files: InputError naming the second of two that resolve to the same file (one would
    overwrite the other, and exit 0)."""
    seen: dict[Path, str] = {}
    for flag, path in paths.items():
        if path is None:
            continue
        target = Path(path).resolve()
        if target in seen:
            raise InputError(path, f"is also {seen[target]}: {flag} and {seen[target]} must name different files")
        seen[target] = flag


def check_creatable(path: Path, folder: Path, below: str) -> None:
    """``folder`` (made if missing) can be made and written in: the nearest existing folder at or above it is a
    folder this user may write in. InputError naming ``path`` otherwise, ``below`` saying what cannot be done."""
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir():
        raise InputError(path, f"{folder} is a file, not a folder: {below}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(path, f"no permission to write in {folder}")


def _safely(ours: Callable[[Path], bool], path: Path) -> bool:
    try:
        return bool(ours(path))
    except (InputError, OSError, UnicodeDecodeError, ValueError):
        return False


def replace_file(path: Path, data: bytes, sync: bool = False) -> None:
    """``data`` into ``path`` through a temporary file in its folder and ``os.replace``, so that readers never see
    a half-written file (``sync``: on the disk before it replaces the old one). A replaced file keeps its
    permissions; a new one gets those a plain open() would give it. A symbolic link stays one: its target is
    written. Raises OSError; the temporary file is removed whatever happens."""
    path = Path(path)
    target = path.resolve() if path.is_symlink() else path
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            if sync:
                f.flush()
                os.fsync(f.fileno())
        try:
            mode = target.stat().st_mode & 0o7777
        except FileNotFoundError:
            umask = os.umask(0)  # mkstemp makes owner-only files
            os.umask(umask)
            mode = 0o666 & ~umask
        os.chmod(tmp, mode)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_file(path: Path, data: bytes | str) -> None:
    """``data`` into ``path``, whole or not at all (``replace_file``, synced); InputError naming ``path`` when the
    write fails (a full disk, a read-only file system): the file as it was stays."""
    path = Path(path)
    try:
        replace_file(path, data.encode() if isinstance(data, str) else data, sync=True)
    except OSError as err:
        target = path.resolve() if path.is_symlink() else path
        kept = "the file as it was is kept" if target.exists() else "nothing was written"
        raise InputError(path, f"could not be written ({err.strerror or err}); {kept}") from err


class OutputLock:
    """An exclusive lock on writing ``path`` for as long as this process holds it (``acquire``/``release``, or a
    ``with`` block): a lock file ``.NAME.lock`` beside it holds the writer's pid. A second ``acquire`` of the same
    path, by any process, raises InputError naming the holder's pid. Advisory: only our commands take it."""

    def __init__(self, path: Path, flag: str = "--out"):
        self.path, self.flag = Path(path), flag
        target = self.path.resolve()
        self.lock_path = target.parent / f".{target.name}.lock"
        self._fd: int | None = None

    def acquire(self) -> "OutputLock":
        try:
            self.lock_path.parent.mkdir(parents=True, exist_ok=True)
            fd = self._lock()
        except OSError as err:  # a full disk, a quota, a folder that refuses new files
            raise InputError(self.path, f"cannot take the lock file {self.lock_path} ({err.strerror or err}); "
                                        "nothing was written") from err
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError as err:
            # Ours alone (we hold it): removed, so that a full disk leaves no empty lock file behind.
            self.lock_path.unlink(missing_ok=True)
            os.close(fd)
            raise InputError(self.path, f"cannot write the lock file {self.lock_path} ({err.strerror or err}); "
                                        "nothing was written") from err
        self._fd = fd
        return self

    def _lock(self) -> int:
        """The lock file, opened and exclusively locked -> its descriptor; InputError if another run holds it."""
        while True:
            fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as err:
                if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    os.close(fd)
                    raise
                holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
                os.close(fd)
                raise InputError(self.path, f"is being written by another run (pid {holder}); wait for it to "
                                            f"finish, or choose another {self.flag}") from None
            # The holder before us may have removed the lock file between our open and our lock: lock the file
            # that is at the path now.
            try:
                same = os.fstat(fd).st_ino == os.stat(self.lock_path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                return fd
            os.close(fd)

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            self.lock_path.unlink(missing_ok=True)
        except OSError:
            pass
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


@contextmanager
def folder_lock(folder: Path) -> Iterator[None]:
    """Hold an exclusive lock on writing in ``folder`` (made if missing; the lock file ``.lock`` in it) for a short
    check-then-write, waiting for another process holding it: two writers of one folder (two ``serve`` on one
    --sessions-dir) then see each other's files, so that a check like "no file of that name yet" stays true until
    the write."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing drops the lock
