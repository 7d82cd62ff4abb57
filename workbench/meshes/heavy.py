"""Meshes too heavy to simplify as they are, and saying so while they are simplified.

Choosing a collision shape (``physics.collision``) and a render mesh (``render.depth``) costs time that grows
faster than the face count (trimesh's oriented bounding box is quadratic in the hull's faces; every decimation step
starts from the full mesh): a 1.3M-face model took minutes, in silence, in every worker at once. So a mesh of more
than ``HEAVY_FACES`` faces is first reduced once to ``WORKING_FACES`` (open3d quadric decimation, well under a
millimetre off at these counts) and both choices are made from that; its errors are still measured against the
full mesh where they are measured by rays (the render mesh). ``announced`` says what is being done while it takes
long: a line when a step has taken over ``FIRST_S`` seconds, then one every ``EVERY_S`` seconds, so that no
silence is longer than that. Loading such a model (``io.bop.read_mesh``: reading the file, merging its vertices)
is announced the same way (``loading``), as it takes seconds on every load. The evaluators prepare a problem's
meshes once in the main process (``evaluation.local.prepare_meshes``); the workers then read them from the cache.
The search's geometry (``inference.search.geometry.search_mesh``) is computed from the render mesh of a heavy model, its
stable poses from a hull of at most ``resting.MAX_HULL_VERTICES`` vertices, and the lowest points of its particles
from a sample of its vertices (``lowest_points``: the convex hull of a 1.3M-face sphere, whose 655k vertices all
lie on it, took 14 s).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

HEAVY_FACES = 200_000
WORKING_FACES = 100_000
FIRST_S = 2.0
EVERY_S = 8.0  # under the 10 s of silence users are promised, with room for a busy machine

_WORKING: dict[str, trimesh.Trimesh] = {}


def faces_text(n: int) -> str:
    return f"{n / 1e6:.1f}M" if n >= 1e6 else f"{n / 1e3:.0f}k" if n >= 1e4 else str(n)


# A mesh file over this size is announced while it loads when its face count cannot be read from its header.
HEAVY_FILE_BYTES = 16_000_000
# ``lowest_points`` searches at most this many of a mesh's vertices (seeded), this many heights at a time.
LOWEST_SAMPLE = 50_000
_LOWEST_CHUNK = 8_000_000


def ply_faces(path: Path) -> int | None:
    """The face count a PLY file's header declares (``element face N``), or None: not a PLY, or no such line in
    its first 64 kB. Reads only the header."""
    try:
        with open(path, "rb") as f:
            head = f.read(65536)
    except OSError:
        return None
    if not head.startswith(b"ply"):
        return None
    for line in head.split(b"end_header")[0].splitlines():
        words = line.split()
        if len(words) == 3 and words[0] == b"element" and words[1] == b"face" and words[2].isdigit():
            return int(words[2])
    return None


def loading(path: Path):
    """A context for loading the mesh file ``path``: ``announced`` ("loading obj_000006.ply (1.3M faces)", not
    cached) when the file is heavy (over ``HEAVY_FACES`` faces by its PLY header, else over ``HEAVY_FILE_BYTES``),
    nothing at all for a light one (not even the announcing process)."""
    faces = ply_faces(path)
    if faces is not None:
        heavy, size = faces > HEAVY_FACES, f"{faces_text(faces)} faces"
    else:
        try:
            nbytes = path.stat().st_size
        except OSError:
            nbytes = 0
        heavy, size = nbytes > HEAVY_FILE_BYTES, f"{nbytes / 1e6:.0f} MB"
    if not heavy:
        return contextlib.nullcontext()
    return announced(f"loading {path.name} ({size})", first_s=FIRST_S, cached=False)


def lowest_points(rotations: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Rotations (n, 3, 3), a heavy mesh's vertices (V, 3) -> (n,) each rotated mesh's lowest z, from at most
    ``LOWEST_SAMPLE`` of its vertices (the same ones every time): no convex hull (a 1.3M-face sphere's, all its
    655k vertices, took 14 s) and not every vertex for every rotation (31 s for 1,444 particles of that sphere).
    A dense mesh's sampled vertices lie a fraction of a millimetre apart (the sphere's lowest points came within
    0.01 mm), where the heights they serve are drawn over centimetres."""
    vertices = np.asarray(vertices, dtype=np.float64)
    if len(vertices) > LOWEST_SAMPLE:
        vertices = vertices[np.random.default_rng(0).choice(len(vertices), LOWEST_SAMPLE, replace=False)]
    rows = np.asarray(rotations, dtype=np.float64)[:, 2, :]  # z of R @ v is R[2] . v
    step = max(1, _LOWEST_CHUNK // max(len(vertices), 1))
    out = np.empty(len(rows))
    for i in range(0, len(rows), step):
        out[i:i + step] = np.min(vertices @ rows[i:i + step].T, axis=0)
    return out


def heavy_models(models) -> str:
    """The models of over ``HEAVY_FACES`` faces as a user knows them ("obj_000006.ply (1.3M faces)", joined by
    commas); "" when there are none."""
    return ", ".join(f"{m.source.name if m.source is not None else m.name} ({faces_text(len(m.mesh.faces))} faces)"
                     for m in models if len(m.mesh.faces) > HEAVY_FACES)


def announced_if(heavy: str, what: str):
    """``announced(what + " with " + heavy)``, not cached, where ``heavy`` (``heavy_models``) names any heavy
    model; nothing at all (not even the announcing process) where it is empty: a frame of light models goes as it
    always went."""
    return announced(f"{what} with {heavy}", first_s=FIRST_S, cached=False) if heavy else contextlib.nullcontext()


def mesh_key(mesh: trimesh.Trimesh) -> str:
    """A digest of the mesh's vertices and faces: the same shape loaded again (the next frame's models) has the
    same key."""
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return h.hexdigest()


def working_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` itself up to ``HEAVY_FACES`` faces, else its quadric decimation to ``WORKING_FACES`` (once per
    process and mesh)."""
    if len(mesh.faces) <= HEAVY_FACES:
        return mesh
    key = mesh_key(mesh)
    if key not in _WORKING:
        import open3d as o3d

        source = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=np.float64)),
                                           o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)))
        simple = source.simplify_quadric_decimation(target_number_of_triangles=WORKING_FACES)
        _WORKING[key] = trimesh.Trimesh(np.asarray(simple.vertices), np.asarray(simple.triangles))
    return _WORKING[key]


@contextlib.contextmanager
def one_at_a_time(key: str, folder: Path):
    """Hold an advisory lock (``flock``) named by ``key`` in ``folder`` for the block: processes preparing the
    same mesh (Ray tasks of one node, two runs started together) take turns, so that the first simplifies it and
    the others find it cached, instead of each computing the same side by side. Without a place for the lock (a
    read-only cache), the block runs unlocked."""
    import fcntl

    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / f"{key}.lock", os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing releases the lock


# The speaker waits on its stdin, a pipe from this process: the pipe closes when this process ends however it ends
# (killed, too), and the speaker then stops, instead of announcing a finished run's work for ever.
_HEARTBEAT = """
import select, sys, time
what, first, every = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
t0 = time.monotonic()
def gone(wait):
    return bool(select.select([sys.stdin], [], [], wait)[0])
if gone(first):
    sys.exit()
print(f"workbench: {what} ...", file=sys.stderr, flush=True)
while not gone(every):
    print(f"workbench: still {what} ({time.monotonic() - t0:.0f} s)", file=sys.stderr, flush=True)
"""


@contextlib.contextmanager
def announced(what: str, first_s: float = FIRST_S, every_s: float = EVERY_S, cached: bool = True):
    """Run the block; if it takes over ``first_s`` seconds, say ``what`` on stderr, then that it goes on every
    ``every_s`` seconds, and how long it took at the end (with "cached for later runs" where ``cached``: its result
    is kept on disk). Quick blocks (a cache hit) say nothing. The lines come from a small process of their own: the
    simplifying libraries hold Python's GIL for a minute at a time, so a thread here could not speak meanwhile."""
    t0 = time.perf_counter()
    try:
        speaker = subprocess.Popen([sys.executable, "-S", "-c", _HEARTBEAT, what, str(first_s), str(every_s)],
                                   stdin=subprocess.PIPE, stdout=subprocess.DEVNULL)
    except OSError:
        speaker = None  # no process to spare: work in silence rather than not at all
    finished = False
    try:
        yield
        finished = True
    finally:
        if speaker is not None:
            speaker.kill()
            speaker.wait()
            speaker.stdin.close()
        took = time.perf_counter() - t0
        if finished and took > first_s:  # not "done" when it failed or was stopped
            print(f"workbench: done {what} in {took:.0f} s" + (" (cached for later runs)" if cached else ""),
                  file=sys.stderr, flush=True)
