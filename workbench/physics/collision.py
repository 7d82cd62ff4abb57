"""What an object collides as in the physics projection: the simplest shape whose measured fit is good enough.

Bullet collides dynamic bodies only as convex shapes (or compounds of them), and its cost per contact grows with
the vertices of a hull. So each mesh gets, in this order of preference:

1. a **box** or a **cylinder** primitive, when the mesh fills it (volume ``>= primitive_fill``) and the two
   surfaces are close (``deviation <= primitive_deviation``): YCB's boxes with rounded edges collide as boxes,
   cans as cylinders. Exact, and the cheapest shapes Bullet has;
2. a **convex** hull reduced to at most ``max_hull_vertices`` vertices, when the mesh fills its hull
   (``>= convex_fill``);
3. a **compound** of a few small convex pieces by V-HACD, for concave meshes (mug, bowl). About a second per
   mesh, hence cached.

Every choice carries its measured fit (``CollisionShape.fit_volume``, ``fit_deviation``) so that benchmarks and the
UI can show it, and the kind can be forced per object (``kind=``; ``PhysicsConfig.shape_overrides``). Kind
"reference" is the unsimplified geometry (the hull of all vertices, or fine V-HACD pieces), the yardstick the
simplified shapes are measured against. Chosen shapes are cached in memory and on disk (one .npz per mesh and
settings), so worker processes and later runs do not recompute them.
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
import trimesh

from workbench.errors import InputError
from workbench.geometry import make_pose
from workbench.meshes import cache
from workbench.meshes.heavy import working_mesh
from workbench.physics.bullet import pybullet

BOX, CYLINDER, CONVEX, COMPOUND = "box", "cylinder", "convex", "compound"
REFERENCE = "reference"
KINDS = (BOX, CYLINDER, CONVEX, COMPOUND)

# V-HACD settings: few pieces (depth 4: at most 16) of few vertices. Part of the cache key.
VHACD_PARAMS = {"resolution": 100000, "maxNumVerticesPerCH": 24, "concavity": 0.005, "depth": 4}
# The unsimplified yardstick: V-HACD as fine as it reasonably goes.
VHACD_REFERENCE_PARAMS = {"resolution": 400000, "maxNumVerticesPerCH": 256, "concavity": 0.001}
# Bump when the choice or the fit measurement changes: old cache files are then ignored.
_CACHE_VERSION = 4  # 4: files carry a checksum (workbench.cache)
_FIT_SAMPLES = 4000


@dataclass(frozen=True)
class CollisionShape:
    """An object's collision geometry, in the object (mesh) frame.

    ``kind`` "box": a box of ``half_extents`` (3,), whose frame in the object frame is ``T_obj_shape`` (4, 4).
    ``kind`` "cylinder": radius ``half_extents[0]`` (= ``half_extents[1]``) and half height ``half_extents[2]``
    along the z axis of ``T_obj_shape`` (Bullet's cylinder axis is its local z).
    ``kind`` "convex" / "compound": ``parts``, the vertices (N_i, 3) of one / several convex pieces
    (``T_obj_shape`` is the identity).
    ``fit_volume``: the mesh's volume over the shape's (1 = exact; < 1 where the shape is larger).
    ``fit_deviation``: metres, the larger of the two 95th percentiles of surface-to-surface distance (mesh samples
    to the shape's surface, shape samples to the mesh's).
    """

    kind: str
    T_obj_shape: np.ndarray = field(default_factory=lambda: np.eye(4))
    half_extents: np.ndarray | None = None
    parts: tuple[np.ndarray, ...] = ()
    fit_volume: float = float("nan")
    fit_deviation: float = float("nan")

    @property
    def n_vertices(self) -> int:
        """Vertices Bullet collides with: 8 for a box, 0 for a cylinder (analytic), else the parts' total."""
        return 8 if self.kind == BOX else sum(len(p) for p in self.parts)

    def describe(self) -> str:
        """One line for tables and the UI: "box (fills 94 %, 1.8 mm)", "convex 64 v (...)", "compound 3 parts
        72 v (...)": the kind, its size, the mesh's share of its volume and the surface deviation."""
        size = {CONVEX: f" {self.n_vertices} v", COMPOUND: f" {len(self.parts)} parts {self.n_vertices} v"}
        return (f"{self.kind}{size.get(self.kind, '')} (fills {100 * self.fit_volume:.0f} %, "
                f"{1e3 * self.fit_deviation:.1f} mm)")

    def support_points(self) -> np.ndarray:
        """Points whose convex hulls make up the shape, in the object frame: box corners, two 64-gons for a
        cylinder's rims (within 0.12 % of its radius), or all part vertices. The lowest point of the shape in any
        pose is one of them. -> (N, 3)."""
        if self.kind == BOX:
            signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
            local = signs * self.half_extents
        elif self.kind == CYLINDER:
            a = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
            r, h = self.half_extents[0], self.half_extents[2]
            rim = np.stack([r * np.cos(a), r * np.sin(a), np.full_like(a, h)], axis=1)
            local = np.concatenate([rim, rim * [1.0, 1.0, -1.0]])
        else:
            return np.concatenate(self.parts, axis=0)
        return local @ self.T_obj_shape[:3, :3].T + self.T_obj_shape[:3, 3]

    def primitive_mesh(self) -> trimesh.Trimesh:
        """The shape as a triangle mesh in the object frame (for fit measurement and display)."""
        if self.kind == BOX:
            return trimesh.creation.box(extents=2.0 * self.half_extents, transform=self.T_obj_shape)
        if self.kind == CYLINDER:
            return trimesh.creation.cylinder(radius=self.half_extents[0], height=2.0 * self.half_extents[2],
                                             sections=64, transform=self.T_obj_shape)
        return trimesh.util.concatenate([trimesh.convex.convex_hull(p) for p in self.parts])


def default_cache_dir() -> Path:
    """Where chosen shapes and convex decompositions are kept between runs: ``$XDG_CACHE_HOME/workbench/vhacd``."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "workbench" / "vhacd"


def collision_shape_for(
    mesh: trimesh.Trimesh,
    primitive_fill: float = 0.85,
    primitive_deviation: float = 6e-3,
    convex_fill: float = 0.8,
    max_hull_vertices: int = 64,
    kind: str | None = None,
    cache_dir: str | os.PathLike | None = None,
) -> CollisionShape:
    """Choose and build the collision shape of ``mesh`` (metres), with its measured fit.

    The thresholds are measured: YCB's sugar and pudding boxes (rounded, slightly bulging) fill 87-88 % of their
    box with a 3.4-5.8 mm deviation, the master chef can 91 % of its cylinder (3.7 mm); with these as primitives
    the true resting scenes of ycbv-real-dev stay a median 1.3 mm from their poses with the unsimplified shapes
    (benchmarks/true_scene_drift.py --reference).

    ``kind``: None chooses (see the module doc); "box", "cylinder", "convex", "compound" force that kind;
    "reference" gives the unsimplified geometry. A mesh that is not watertight has no meaningful volume: it is
    measured and collides as its convex hull, and may still be a primitive. Cached under ``cache_dir`` (default
    ``default_cache_dir()``).
    """
    if len(mesh.vertices) < 4 or not np.all(np.isfinite(mesh.vertices)):
        raise InputError("mesh", "needs at least 4 finite vertices to have a volume")
    if kind not in (None, REFERENCE) + KINDS:
        raise InputError("collision kind", f"must be one of {', '.join(KINDS + (REFERENCE,))}, not {kind!r}")
    settings = (primitive_fill, primitive_deviation, convex_fill, max_hull_vertices, kind)
    key = _mesh_key(mesh, repr(settings), repr(sorted(VHACD_PARAMS.items())), str(_CACHE_VERSION))
    return _cached(key, cache_dir, lambda: _choose(mesh, *settings, cache_dir=cache_dir))


def _choose(mesh, primitive_fill, primitive_deviation, convex_fill, max_hull_vertices, kind, cache_dir):
    mesh = working_mesh(mesh)  # a mesh of over HEAVY_FACES faces: chosen from its 100k-face decimation
    solid = mesh if mesh.is_watertight else mesh.convex_hull
    volume = abs(float(solid.volume))
    surface = _SurfaceDistance(solid)
    if kind == REFERENCE:
        if volume >= convex_fill * float(solid.convex_hull.volume):
            return _measured(CollisionShape(CONVEX, parts=(_hull_vertices(solid.vertices),)), solid, volume, surface)
        parts = _run_vhacd(solid, VHACD_REFERENCE_PARAMS)
        return _measured(CollisionShape(COMPOUND, parts=parts), solid, volume, surface)
    if kind in (None, BOX, CYLINDER):
        candidates = []
        if kind in (None, BOX):
            T, half = _bounding_box(solid)
            candidates.append(_measured(CollisionShape(BOX, T_obj_shape=T, half_extents=half), solid, volume, surface))
        if kind in (None, CYLINDER):
            T, half = _bounding_cylinder(solid)
            candidates.append(
                _measured(CollisionShape(CYLINDER, T_obj_shape=T, half_extents=half), solid, volume, surface))
        if kind is not None:
            return candidates[0]
        good = [c for c in candidates if c.fit_volume >= primitive_fill and c.fit_deviation <= primitive_deviation]
        if good:
            return max(good, key=lambda c: c.fit_volume)
    hull = solid.convex_hull
    if kind == CONVEX or (kind is None and volume >= convex_fill * float(hull.volume)):
        shape = CollisionShape(CONVEX, parts=(_reduced_hull(hull, max_hull_vertices),))
        return _measured(shape, solid, volume, surface)
    parts = tuple(_reduced_hull(trimesh.convex.convex_hull(p), max_hull_vertices)
                  for p in _run_vhacd(solid, VHACD_PARAMS))
    return _measured(CollisionShape(COMPOUND if len(parts) > 1 else CONVEX, parts=parts), solid, volume, surface)


class _SurfaceDistance:
    """Unsigned distances to one mesh's surface (open3d ray-casting scene), and samples of that surface."""

    def __init__(self, mesh: trimesh.Trimesh):
        import open3d as o3d

        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                                  o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))
        self.samples = _surface_samples(mesh)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) -> (N,) metres to the surface."""
        import open3d as o3d

        return self._scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy().astype(np.float64)

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) -> (N,) metres to the surface, negative inside (the mesh must be closed)."""
        import open3d as o3d

        return self._scene.compute_signed_distance(
            o3d.core.Tensor(points.astype(np.float32))).numpy().astype(np.float64)


def _surface_samples(mesh: trimesh.Trimesh) -> np.ndarray:
    """Seeded samples of a surface, so a shape's measured fit is reproducible. -> (_FIT_SAMPLES, 3)."""
    return np.asarray(trimesh.sample.sample_surface(mesh, _FIT_SAMPLES, seed=0)[0], dtype=np.float64)


def _measured(shape: CollisionShape, solid: trimesh.Trimesh, volume: float,
              surface: _SurfaceDistance) -> CollisionShape:
    """``shape`` with its fit to ``solid`` (volume ``volume``) filled in.

    The deviation counts what changes contacts: the shape's surface where it stands off the mesh (rounded edges
    under a box's corners, a bottle's neck inside its hull), and the mesh's surface where it sticks out of the
    shape. Mesh surface inside the shape (the hollow of a concave side) does not touch anything either way; the
    volume ratio accounts for it.
    """
    pieces = [shape.primitive_mesh()] if shape.kind in (BOX, CYLINDER) else [
        trimesh.convex.convex_hull(p) for p in shape.parts]
    shape_volume = sum(abs(float(p.volume)) for p in pieces)  # pieces overlap a little: close enough
    samples = _surface_samples(trimesh.util.concatenate(pieces))
    # Mesh samples outside every piece: the smallest signed distance (> 0 outside) over the pieces.
    outside = np.min([_SurfaceDistance(p).signed_distance(surface.samples) for p in pieces], axis=0)
    stands_off = surface.distance(samples)
    deviation = max(float(np.percentile(np.maximum(outside, 0.0), 95)), float(np.percentile(stands_off, 95)))
    return CollisionShape(shape.kind, shape.T_obj_shape, shape.half_extents, shape.parts,
                          fit_volume=volume / shape_volume, fit_deviation=deviation)


def _hull_vertices(points: np.ndarray) -> np.ndarray:
    """Vertices of the convex hull of ``points`` (N, 3) -> (M, 3) float64."""
    return np.asarray(trimesh.convex.convex_hull(np.asarray(points, dtype=np.float64)).vertices, dtype=np.float64)


def _reduced_hull(hull: trimesh.Trimesh, max_vertices: int) -> np.ndarray:
    """Vertices (<= max_vertices, 3) of a convex hull close to ``hull``: quadric decimation of the hull's
    surface (open3d), which keeps the vertices that matter to its shape, then the hull of what is left."""
    import open3d as o3d

    vertices = np.asarray(hull.vertices, dtype=np.float64)
    target = 2 * (max_vertices - 2)  # faces of a closed triangulated surface with max_vertices vertices
    while len(vertices) > max_vertices and target >= 4:
        o3d_mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(hull.vertices)),
                                             o3d.utility.Vector3iVector(np.asarray(hull.faces)))
        simple = o3d_mesh.simplify_quadric_decimation(target_number_of_triangles=target)
        vertices = _hull_vertices(np.asarray(simple.vertices))
        target -= max(2, target // 8)
    return vertices


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


def _bounding_cylinder(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """The smallest enclosing cylinder whose axis is one of the axes of the mesh's bounding box (the object
    frame's or the oriented box's): (T_obj_cylinder (4, 4), (r, r, half height)). The axis is the frame's z.
    Its centre line goes through the middle of the vertices' extent across the axis, a good enough centre for
    the round meshes this is meant for (a poorly centred cylinder simply fits badly and is not chosen)."""
    T_box, _ = _bounding_box(mesh)
    frames = [np.eye(3), T_box[:3, :3]]
    points = np.asarray(mesh.convex_hull.vertices, dtype=np.float64)
    best = None
    for R in frames:
        for axis in range(3):
            # A right-handed frame whose z is this axis.
            Rc = np.roll(R, 2 - axis, axis=1)
            local = points @ Rc
            lo, hi = local.min(axis=0), local.max(axis=0)
            centre = (lo + hi) / 2.0
            r = float(np.max(np.linalg.norm(local[:, :2] - centre[:2], axis=1)))
            h = float(hi[2] - lo[2]) / 2.0
            volume = np.pi * r * r * 2.0 * h
            if best is None or volume < best[0] * (1.0 - 1e-9):
                best = (volume, make_pose(Rc, Rc @ centre), np.array([r, r, h]))
    return best[1], best[2]


_MEMORY_CACHE: dict[str, CollisionShape] = {}


def _cached(key: str, cache_dir, compute) -> CollisionShape:
    """The shape under ``key`` from memory, else disk, else ``compute()`` (then stored in both)."""
    if key in _MEMORY_CACHE:
        return _MEMORY_CACHE[key]
    path = Path(cache_dir or default_cache_dir()) / f"{key}.npz"
    shape = cache.load(path, _shape_from_arrays)
    if shape is None:
        shape = compute()
        cache.save(path, dict(kind=np.array(shape.kind), T_obj_shape=shape.T_obj_shape,
                              half_extents=np.zeros(0) if shape.half_extents is None else shape.half_extents,
                              n_parts=np.array(len(shape.parts)), fit_volume=np.array(shape.fit_volume),
                              fit_deviation=np.array(shape.fit_deviation),
                              **{f"part{i}": p for i, p in enumerate(shape.parts)}))
    _MEMORY_CACHE[key] = shape
    return shape


def _shape_from_arrays(data: dict[str, np.ndarray]) -> CollisionShape:
    """A cached shape's arrays -> the shape; ValueError when they do not make one."""
    shape = CollisionShape(
        str(data["kind"]), np.asarray(data["T_obj_shape"], dtype=np.float64).reshape(4, 4),
        data["half_extents"] if data["half_extents"].size else None,
        tuple(data[f"part{i}"] for i in range(int(data["n_parts"]))),
        float(data["fit_volume"]), float(data["fit_deviation"]))
    if shape.kind not in KINDS or not np.isfinite(shape.T_obj_shape).all():
        raise ValueError(f"it holds no collision shape (kind {shape.kind!r})")
    if any(np.asarray(p).ndim != 2 or np.asarray(p).shape[1] != 3 for p in shape.parts):
        raise ValueError("its convex pieces are not (N, 3) vertex arrays")
    return shape


def _mesh_key(mesh: trimesh.Trimesh, *extra: str) -> str:
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    for e in extra:
        h.update(e.encode())
    return h.hexdigest()


def _run_vhacd(mesh: trimesh.Trimesh, params: dict) -> tuple[np.ndarray, ...]:
    """Convex pieces of ``mesh`` by V-HACD -> tuple of hull vertex arrays (N_i, 3) in the mesh frame."""
    with tempfile.TemporaryDirectory() as tmp:
        src, dst, log = (os.path.join(tmp, n) for n in ("in.obj", "out.obj", "log.txt"))
        mesh.export(src)
        with _stdout_silenced():
            pybullet.vhacd(src, dst, log, **params)
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
