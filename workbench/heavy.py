"""Meshes too heavy to simplify as they are, and saying so while they are simplified.

Choosing a collision shape (``physics.collision``) and a render mesh (``render.depth``) costs time that grows
faster than the face count (trimesh's oriented bounding box is quadratic in the hull's faces; every decimation step
starts from the full mesh): a 1.3M-face model took minutes, in silence, in every worker at once. So a mesh of more
than ``HEAVY_FACES`` faces is first reduced once to ``WORKING_FACES`` (open3d quadric decimation, well under a
millimetre off at these counts) and both choices are made from that; its errors are still measured against the
full mesh where they are measured by rays (the render mesh). ``announced`` says what is being done while it takes
long: a line when a step has taken over ``FIRST_S`` seconds, then one every ``EVERY_S`` seconds, so that no
silence is longer than that. The evaluators prepare a problem's meshes once in the main process
(``evaluation.local.prepare_meshes``); the workers then read them from the cache. The search's geometry
(``inference.context.search_mesh``) is computed from the render mesh of a heavy model, its stable poses from a hull
of at most ``resting.MAX_HULL_VERTICES`` vertices, and the lowest points of its particles from its hull's vertices.
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
EVERY_S = 10.0

_WORKING: dict[str, trimesh.Trimesh] = {}


def faces_text(n: int) -> str:
    return f"{n / 1e6:.1f}M" if n >= 1e6 else f"{n / 1e3:.0f}k" if n >= 1e4 else str(n)


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


_HEARTBEAT = """
import sys, time
what, first, every = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
t0 = time.monotonic()
time.sleep(first)
print(f"workbench: {what} ...", file=sys.stderr, flush=True)
while True:
    time.sleep(every)
    print(f"workbench: still {what} ({time.monotonic() - t0:.0f} s)", file=sys.stderr, flush=True)
"""


@contextlib.contextmanager
def announced(what: str, first_s: float = FIRST_S, every_s: float = EVERY_S):
    """Run the block; if it takes over ``first_s`` seconds, say ``what`` on stderr, then that it goes on every
    ``every_s`` seconds, and how long it took at the end. Quick blocks (a cache hit) say nothing. The lines come
    from a small process of their own: the simplifying libraries hold Python's GIL for a minute at a time, so a
    thread here could not speak meanwhile."""
    t0 = time.perf_counter()
    try:
        speaker = subprocess.Popen([sys.executable, "-S", "-c", _HEARTBEAT, what, str(first_s), str(every_s)],
                                   stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    except OSError:
        speaker = None  # no process to spare: work in silence rather than not at all
    try:
        yield
    finally:
        if speaker is not None:
            speaker.kill()
            speaker.wait()
        took = time.perf_counter() - t0
        if took > first_s:
            print(f"workbench: done {what} in {took:.0f} s (cached for later runs)", file=sys.stderr, flush=True)
