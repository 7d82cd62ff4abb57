"""What an object collides as in the physics projection: an exact box, one convex hull, or convex pieces.

Bullet collides dynamic bodies only as convex shapes (or compounds of them). A box-like mesh collides as its
box, which is exact and the cheapest shape Bullet has; a mesh that fills most of its convex hull collides as the
hull; a concave mesh (mug, bowl) is split into convex pieces by V-HACD, which takes about a second per mesh and is
therefore cached in memory and on disk.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pybullet
import trimesh

from workbench.errors import InputError
from workbench.geometry import make_pose

BOX, CONVEX, COMPOUND = "box", "convex", "compound"

# V-HACD settings; part of the cache key, so changing them recomputes the decompositions.
VHACD_PARAMS = {"resolution": 100000, "maxNumVerticesPerCH": 64, "concavity": 0.0025}


@dataclass(frozen=True)
class CollisionShape:
    """An object's collision geometry, in the object (mesh) frame.

    ``kind`` "box": a box of ``half_extents`` (3,) whose frame in the object frame is ``T_obj_shape`` (4, 4).
    ``kind`` "convex" / "compound": ``parts``, the vertices (N_i, 3) of one / several convex pieces
    (``T_obj_shape`` is the identity).
    """

    kind: str
    T_obj_shape: np.ndarray = field(default_factory=lambda: np.eye(4))
    half_extents: np.ndarray | None = None
    parts: tuple[np.ndarray, ...] = ()

    def support_points(self) -> np.ndarray:
        """Points whose convex hulls make up the shape, in the object frame: box corners or all part vertices.
        The lowest point of the shape in any pose is one of them. -> (N, 3)."""
        if self.kind == BOX:
            signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
            corners = signs * self.half_extents
            return corners @ self.T_obj_shape[:3, :3].T + self.T_obj_shape[:3, 3]
        return np.concatenate(self.parts, axis=0)


def default_cache_dir() -> Path:
    """Where convex decompositions are kept between runs: ``$XDG_CACHE_HOME/workbench/vhacd``."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "workbench" / "vhacd"


def collision_shape_for(
    mesh: trimesh.Trimesh,
    box_fill: float = 0.9,
    convex_fill: float = 0.8,
    cache_dir: str | os.PathLike | None = None,
) -> CollisionShape:
    """Choose and build the collision shape of ``mesh``.

    A watertight mesh whose volume is at least ``box_fill`` of its (oriented) bounding box's collides as that
    box; one that fills at least ``convex_fill`` of its convex hull collides as the hull; anything more concave is
    decomposed with V-HACD (cached under ``cache_dir``, default ``default_cache_dir()``). A mesh that is not
    watertight has no meaningful volume and collides as its convex hull.
    """
    if len(mesh.vertices) < 4 or not np.all(np.isfinite(mesh.vertices)):
        raise InputError("mesh", "needs at least 4 finite vertices to have a volume")
    if not mesh.is_watertight:
        return CollisionShape(CONVEX, parts=(_hull_vertices(mesh.vertices),))
    volume = abs(float(mesh.volume))
    T_obj_box, half_extents = _bounding_box(mesh)
    if volume >= box_fill * float(np.prod(2.0 * half_extents)):
        return CollisionShape(BOX, T_obj_shape=T_obj_box, half_extents=half_extents)
    if volume >= convex_fill * float(mesh.convex_hull.volume):
        return CollisionShape(CONVEX, parts=(_hull_vertices(mesh.vertices),))
    parts = convex_decomposition(mesh, cache_dir)
    return CollisionShape(COMPOUND if len(parts) > 1 else CONVEX, parts=parts)


def _hull_vertices(points: np.ndarray) -> np.ndarray:
    """Vertices of the convex hull of ``points`` (N, 3) -> (M, 3) float64."""
    return np.asarray(trimesh.convex.convex_hull(np.asarray(points, dtype=np.float64)).vertices, dtype=np.float64)


def _bounding_box(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """The smaller of the axis-aligned and the minimum-volume oriented bounding box: (T_obj_box (4, 4),
    half extents (3,)). The axis-aligned one wins ties, so an axis-aligned box mesh gets an exact identity frame
    rather than the oriented box's rotation with 1e-16 noise."""
    lo, hi = mesh.bounds
    aabb = (make_pose(np.eye(3), (lo + hi) / 2.0), (hi - lo) / 2.0)
    obb = mesh.bounding_box_oriented.primitive
    if np.prod(obb.extents) >= np.prod(hi - lo) * (1.0 - 1e-6):
        return aabb
    T = np.array(obb.transform, dtype=np.float64)
    if np.linalg.det(T[:3, :3]) < 0:
        T[:3, 2] *= -1.0  # the same box in a right-handed frame
    return T, np.asarray(obb.extents, dtype=np.float64) / 2.0


_MEMORY_CACHE: dict[str, tuple[np.ndarray, ...]] = {}


def convex_decomposition(mesh: trimesh.Trimesh, cache_dir: str | os.PathLike | None = None) -> tuple[np.ndarray, ...]:
    """Convex pieces of ``mesh`` by V-HACD: a tuple of hull vertex arrays (N_i, 3) in the mesh frame.

    Cached in memory and in ``cache_dir`` (one .npz per mesh, keyed by its geometry and ``VHACD_PARAMS``), so a
    reloaded session or another worker process gets the same pieces without recomputing them.
    """
    key = _mesh_key(mesh)
    if key in _MEMORY_CACHE:
        return _MEMORY_CACHE[key]
    path = Path(cache_dir or default_cache_dir()) / f"{key}.npz"
    if path.exists():
        with np.load(path) as data:
            parts = tuple(data[f"part{i}"] for i in range(len(data.files)))
    else:
        parts = _run_vhacd(mesh)
        path.parent.mkdir(parents=True, exist_ok=True)
        # Write then rename: worker processes may decompose the same mesh at the same time.
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **{f"part{i}": p for i, p in enumerate(parts)})
        os.replace(tmp, path)
    _MEMORY_CACHE[key] = parts
    return parts


def _mesh_key(mesh: trimesh.Trimesh) -> str:
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    h.update(repr(sorted(VHACD_PARAMS.items())).encode())
    return h.hexdigest()


def _run_vhacd(mesh: trimesh.Trimesh) -> tuple[np.ndarray, ...]:
    with tempfile.TemporaryDirectory() as tmp:
        src, dst, log = (os.path.join(tmp, n) for n in ("in.obj", "out.obj", "log.txt"))
        mesh.export(src)
        with _stdout_silenced():
            pybullet.vhacd(src, dst, log, **VHACD_PARAMS)
        parts = _read_obj_objects(Path(dst))
    if not parts:
        raise InputError("mesh", "V-HACD found no convex pieces in it")
    return tuple(_hull_vertices(p) for p in parts)


def _read_obj_objects(path: Path) -> list[np.ndarray]:
    """Vertices of each ``o`` object of a Wavefront OBJ written by V-HACD -> list of (N_i, 3)."""
    parts: list[list[list[float]]] = []
    for line in path.read_text().splitlines():
        if line.startswith("o "):
            parts.append([])
        elif line.startswith("v ") and parts:
            parts[-1].append([float(x) for x in line.split()[1:4]])
    return [np.asarray(p, dtype=np.float64) for p in parts if len(p) >= 4]


@contextlib.contextmanager
def _stdout_silenced():
    """V-HACD prints its progress from C straight to file descriptor 1: point it at /dev/null meanwhile."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
