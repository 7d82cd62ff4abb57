"""Synthetic test scenes of the paper's cases, written as a BOP dataset.

Categories (Desingh et al. 2016, Sec. V): ``touching`` (two boxes in face or edge contact), ``stacked`` (a
smaller box resting on a larger one near its edge), ``slant`` (a box leaning on another box and the table),
``occluded`` (a small box hidden behind a tall one), ``three`` and ``four`` (clutter mixing those relations).

Every scene is laid out from *relations* (touch / stack / slant / hide), each new box moved along one degree of
freedom by bisection until it just touches its partner, then settled by physics in this module's own pybullet
world (independent of ``physics.py``) and kept only when the settled scene still is what its relations say
(contacts from ``getContactPoints``, tilt, visibility); otherwise the next random draw is tried. Depth is
ray-cast with open3d (independent of the estimator's OpenGL renderer) and degraded by ``sensor.py``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d
import pybullet as pb
import trimesh
from PIL import Image

from workbench import bop
from workbench.geometry import (
    invert_pose, make_pose, matrix_to_quat_wxyz, quat_wxyz_to_matrix, rot_z, wxyz_to_xyzw, xyzw_to_wxyz,
)
from workbench.errors import InputError
from workbench.metrics import box_symmetries
from workbench.sensor import SensorModel, apply_sensor

CATEGORIES = ("touching", "stacked", "slant", "occluded", "three", "four")
EZ = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Box:
    obj_id: int
    name: str
    extents: tuple[float, float, float]  # metres, along the model's x, y, z


# YCB-like boxes (the paper used YCB objects).
BOXES = (
    Box(1, "cracker_box", (0.16, 0.06, 0.21)),
    Box(2, "sugar_box", (0.09, 0.045, 0.175)),
    Box(3, "pudding_box", (0.11, 0.089, 0.035)),
    Box(4, "gelatin_box", (0.089, 0.073, 0.028)),
    Box(5, "wood_block", (0.085, 0.085, 0.2)),
    Box(6, "foam_brick", (0.05, 0.075, 0.05)),
)
BOX_BY_ID = {b.obj_id: b for b in BOXES}
TALL = (1, 2, 5)  # long enough to lean, tall enough to hide behind
SMALL = (3, 4, 6)


@dataclass(frozen=True)
class SynthConfig:
    """How scenes are drawn, simulated, viewed and sensed. Lengths metres, angles degrees."""

    width: int = 640
    height: int = 480
    focal_640: float = 525.0  # Kinect v1 focal length at 640 pixels wide; scaled with the width
    table_size: tuple[float, float] = (1.2, 0.8)
    table_thickness: float = 0.04
    floor_z: float = -0.75
    cam_distance: tuple[float, float] = (0.7, 1.0)
    cam_elevation: tuple[float, float] = (45.0, 70.0)
    hide_azimuth_jitter: float = 15.0  # camera azimuth spread around "the tall box is in front of the small one"
    dt: float = 1.0 / 1000.0
    settle_max_s: float = 3.0
    rest_speed: float = 2e-3  # m/s (and rad/s times 0.1 m) below which a body counts as at rest
    rest_steps: int = 100  # ... for this many consecutive steps
    density: float = 400.0  # kg/m^3, filled cardboard boxes
    friction: float = 0.75
    lift: float = 3e-4  # boxes start this far above the table and drop onto it
    contact_tol: float = 1e-3  # a contact point this close counts as touching
    flat_tol: float = 3.0  # a box resting on a face tilts less than this
    slant_range: tuple[float, float] = (10.0, 80.0)
    hidden_max_visib: float = 0.1
    shown_min_visib: float = 0.15
    max_layout_tries: int = 300
    max_camera_tries: int = 40
    sensor: SensorModel = field(default_factory=SensorModel)

    def K(self) -> np.ndarray:
        """Kinect-like intrinsics; principal point at the image centre (pixel centres at integer u, v)."""
        f = self.focal_640 * self.width / 640.0
        return np.array([[f, 0.0, (self.width - 1) / 2.0], [0.0, f, (self.height - 1) / 2.0], [0.0, 0.0, 1.0]])


@dataclass
class Placed:
    """One box of a layout. ``relation``: how it was placed relative to ``parent`` (index into the layout)."""

    box: Box
    T: np.ndarray  # (4, 4) T_world_obj
    relation: str = "base"  # base | touch | stack | slant | hide
    parent: int = -1
    body: int = -1


# ----------------------------------------------------------------------------------------------------------------
# Geometry helpers


def box_mesh(extents) -> trimesh.Trimesh:
    """A box centred at its origin, metres."""
    return trimesh.creation.box(extents=np.asarray(extents, dtype=np.float64))


def support_half_extent(R: np.ndarray, extents, direction: np.ndarray) -> float:
    """Half the width of a box with rotation R (3, 3) measured along a unit world direction (3,)."""
    return float(0.5 * np.sum(np.abs(R.T @ direction) * np.asarray(extents)))


def tilt_deg(R: np.ndarray) -> float:
    """How far a box is from resting on a face: the angle between world z and its most vertical axis."""
    return float(np.degrees(np.arccos(np.clip(np.max(np.abs(R[2, :])), -1.0, 1.0))))


def resting_rotation(up_axis: int, yaw: float, flip: bool = False) -> np.ndarray:
    """Rotation of a box lying with its model axis ``up_axis`` vertical, turned by ``yaw`` about world z."""
    R_up = {0: np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),  # x -> z
            1: np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),  # y -> z
            2: np.eye(3)}[up_axis]
    if flip:  # upside down: the same box, a different ground-truth rotation
        R_up = R_up @ np.diag([1.0, -1.0, -1.0]) if up_axis != 0 else R_up @ np.diag([-1.0, 1.0, -1.0])
    return rot_z(yaw) @ R_up


def horizontal_faces(R: np.ndarray) -> list[np.ndarray]:
    """Outward normals (world, unit) of the four side faces of a box resting on a face."""
    axes = [R[:, i] for i in range(3) if abs(R[2, i]) < 0.5]
    return [s * a for a in axes for s in (1.0, -1.0)]


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """T_cam_world of an OpenCV camera at ``eye`` looking at ``target`` with the image's up roughly world z."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, EZ)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return invert_pose(make_pose(np.stack([x, y, z], axis=1), eye))


# ----------------------------------------------------------------------------------------------------------------
# Physics (this module's own pybullet world)


class Sim:
    """A pybullet DIRECT world with a fixed table (top at z = 0) and free boxes."""

    def __init__(self, cfg: SynthConfig):
        self.cfg = cfg
        self.cid = pb.connect(pb.DIRECT)
        self.table = -1

    def close(self) -> None:
        pb.disconnect(self.cid)

    def reset(self) -> None:
        """Empty world with the table; bodies are re-created per scene (a reused world is not deterministic)."""
        c = self.cfg
        pb.resetSimulation(physicsClientId=self.cid)
        pb.setGravity(0, 0, -9.81, physicsClientId=self.cid)
        pb.setPhysicsEngineParameter(fixedTimeStep=c.dt, numSolverIterations=50, physicsClientId=self.cid)
        half = [c.table_size[0] / 2, c.table_size[1] / 2, c.table_thickness / 2]
        shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=self.cid)
        self.table = pb.createMultiBody(0, shape, basePosition=[0, 0, -half[2]], physicsClientId=self.cid)
        pb.changeDynamics(self.table, -1, lateralFriction=c.friction, restitution=0.0, physicsClientId=self.cid)

    def add_box(self, extents, T: np.ndarray) -> int:
        c = self.cfg
        e = np.asarray(extents, dtype=np.float64)
        shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=(e / 2).tolist(), physicsClientId=self.cid)
        body = pb.createMultiBody(
            float(c.density * np.prod(e)), shape, useMaximalCoordinates=True, physicsClientId=self.cid
        )
        pb.changeDynamics(
            body, -1, lateralFriction=c.friction, restitution=0.0, linearDamping=0.04, angularDamping=0.04,
            physicsClientId=self.cid,
        )
        self.set_pose(body, T)
        return body

    def set_pose(self, body: int, T: np.ndarray) -> None:
        q = wxyz_to_xyzw(matrix_to_quat_wxyz(T[:3, :3]))
        pb.resetBasePositionAndOrientation(body, T[:3, 3].tolist(), q.tolist(), physicsClientId=self.cid)
        pb.resetBaseVelocity(body, [0, 0, 0], [0, 0, 0], physicsClientId=self.cid)

    def pose(self, body: int) -> np.ndarray:
        p, q = pb.getBasePositionAndOrientation(body, physicsClientId=self.cid)
        return make_pose(quat_wxyz_to_matrix(xyzw_to_wxyz(np.asarray(q))), np.asarray(p))

    def distance(self, a: int, b: int, horizon: float = 1.0) -> float:
        """Signed closest distance (negative: penetration) between two bodies, capped at ``horizon``."""
        pts = pb.getClosestPoints(a, b, horizon, physicsClientId=self.cid)
        return min((p[8] for p in pts), default=horizon)

    def settle(self, bodies: list[int]) -> bool:
        """Step until every body has been at rest for ``rest_steps`` steps. False if that never happens."""
        c = self.cfg
        calm = 0
        for _ in range(int(c.settle_max_s / c.dt)):
            pb.stepSimulation(physicsClientId=self.cid)
            fast = False
            for b in bodies:
                v, w = pb.getBaseVelocity(b, physicsClientId=self.cid)
                if np.linalg.norm(v) > c.rest_speed or 0.1 * np.linalg.norm(w) > c.rest_speed:
                    fast = True
                    break
            calm = 0 if fast else calm + 1
            if calm >= c.rest_steps:
                return True
        return False

    def touching(self, a: int, b: int) -> bool:
        """Contact points of the last step between a and b closer than ``contact_tol``."""
        pts = pb.getContactPoints(a, b, physicsClientId=self.cid)
        return any(p[8] <= self.cfg.contact_tol for p in pts)


def bisect_contact(sim: Sim, body: int, partner: int, pose_at, s_free: float, s_hit: float) -> np.ndarray | None:
    """Move ``body`` along a one-parameter path ``pose_at(s) -> (4, 4)`` to where it just touches ``partner``.

    ``s_free`` must leave it clear of the partner and ``s_hit`` must make them overlap; None otherwise. The pose
    returned overlaps by a hair (< 1 um): pybullet reports no contact point across even a 0.3 mm gap, so boxes
    placed side by side with any gap would never register as touching."""

    def dist(s: float) -> float:
        sim.set_pose(body, pose_at(s))
        return sim.distance(body, partner)

    if dist(s_free) <= 0 or dist(s_hit) > 0:
        return None
    for _ in range(30):
        mid = 0.5 * (s_free + s_hit)
        if dist(mid) > 0:
            s_free = mid
        else:
            s_hit = mid
    T = pose_at(s_hit)
    sim.set_pose(body, T)
    return T


# ----------------------------------------------------------------------------------------------------------------
# Relations: each places a new box against a box already resting flat on the table


def place_touch(sim: Sim, rng, parent: Placed, box: Box, body: int, edge: bool, hide: bool = False):
    """``box`` on the table against a side face of ``parent``: face to face, or (``edge``) turned so that a
    vertical edge meets the face. ``hide``: lying flat, aligned and centred on the face, to be hidden behind it.
    -> (T_world_obj, outward normal of the parent's face) or None."""
    c_A, R_A = parent.T[:3, 3], parent.T[:3, :3]
    faces = horizontal_faces(R_A)
    n = faces[rng.integers(len(faces))]
    t = np.cross(EZ, n)
    up = int(np.argmin(box.extents)) if hide else int(rng.integers(3))
    yaw_A = np.arctan2(n[1], n[0])
    yaw = yaw_A + rng.integers(4) * np.pi / 2 + (rng.uniform(np.radians(20), np.radians(70)) if edge else 0.0)
    R = resting_rotation(up, yaw, bool(rng.integers(2)))
    hA_n = support_half_extent(R_A, parent.box.extents, n)
    hA_t = support_half_extent(R_A, parent.box.extents, t)
    hB_n = support_half_extent(R, box.extents, n)
    hB_t = support_half_extent(R, box.extents, t)
    if hide:
        room = max(hA_t - hB_t, 0.0)
        lateral = rng.uniform(-room, room) * 0.5
    else:
        lateral = rng.uniform(-0.6, 0.6) * hA_t
    z = support_half_extent(R, box.extents, EZ) + sim.cfg.lift

    def pose_at(s: float) -> np.ndarray:
        p = c_A + n * s + t * lateral
        return make_pose(R, np.array([p[0], p[1], z]))

    T = bisect_contact(sim, body, parent.body, pose_at, hA_n + hB_n + 0.05, hA_n + hB_n - 0.01)
    return None if T is None else (T, n)


def place_stack(sim: Sim, rng, parent: Placed, box: Box, body: int):
    """``box`` lowered onto the top of ``parent``, its centre out towards one edge (it may overhang)."""
    c_A, R_A = parent.T[:3, 3], parent.T[:3, :3]
    faces = horizontal_faces(R_A)
    n = faces[rng.integers(len(faces))]
    t = np.cross(EZ, n)
    up = int(rng.integers(3))
    R = resting_rotation(up, np.arctan2(n[1], n[0]) + rng.uniform(-np.pi, np.pi), bool(rng.integers(2)))
    hA_n = support_half_extent(R_A, parent.box.extents, n)
    hA_t = support_half_extent(R_A, parent.box.extents, t)
    top = c_A[2] + support_half_extent(R_A, parent.box.extents, EZ)
    hB_z = support_half_extent(R, box.extents, EZ)
    xy = c_A + n * hA_n * rng.uniform(0.45, 0.85) + t * hA_t * rng.uniform(-0.3, 0.3)

    def pose_at(s: float) -> np.ndarray:
        return make_pose(R, np.array([xy[0], xy[1], top + hB_z + s]))

    return bisect_contact(sim, body, parent.body, pose_at, 0.05, -0.01)


def place_slant(sim: Sim, rng, parent: Placed, box: Box, body: int):
    """``box`` standing on its bottom edge on the table beside ``parent`` and tipped over onto it."""
    c_A, R_A = parent.T[:3, 3], parent.T[:3, :3]
    faces = horizontal_faces(R_A)
    n = faces[rng.integers(len(faces))]
    t = np.cross(EZ, n)
    e = np.asarray(box.extents)
    long, thin = int(np.argmax(e)), int(np.argmin(e))
    wide = 3 - long - thin
    R0 = np.zeros((3, 3))
    R0[:, long], R0[:, thin], R0[:, wide] = EZ, n, t
    if np.linalg.det(R0) < 0:
        R0[:, wide] = -t
    h, th = e[long], e[thin]
    H_A = c_A[2] + support_half_extent(R_A, parent.box.extents, EZ)
    theta = np.radians(rng.uniform(15.0, 45.0))
    # Pivot distance from the parent's face for the intended lean: the top corner meets the face when the parent is
    # taller than the leaning box's top, else the leaning face rests on the parent's top edge.
    D = h * np.sin(theta) if h * np.cos(theta) <= H_A else H_A * np.tan(theta)
    face = c_A + n * support_half_extent(R_A, parent.box.extents, n)
    pivot = face + n * D + t * rng.uniform(-0.4, 0.4) * support_half_extent(R_A, parent.box.extents, t)
    pivot[2] = sim.cfg.lift
    c0 = pivot + n * th / 2 + EZ * h / 2
    k = np.cross(n, EZ)  # turning about k carries the top towards the parent

    def pose_at(a: float) -> np.ndarray:
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        Rk = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
        return make_pose(Rk @ R0, pivot + Rk @ (c0 - pivot))

    return bisect_contact(sim, body, parent.body, pose_at, 0.0, np.radians(85.0))


# ----------------------------------------------------------------------------------------------------------------
# Layouts per category


def _draw_relations(category: str, rng) -> list[str]:
    """The relations (besides the base box) a scene of ``category`` is built from."""
    single = {"touching": "touch", "stacked": "stack", "slant": "slant", "occluded": "hide"}
    if category in single:
        return [single[category]]
    n = {"three": 2, "four": 3}[category]
    while True:
        rel = [str(r) for r in rng.choice(["touch", "stack", "slant", "hide"], size=n)]
        if len(set(rel)) >= 2 and rel.count("hide") <= 1:
            return rel


def _draw_boxes(relations: list[str], rng) -> list[Box]:
    """Distinct boxes suited to the relations: a tall box hides a small one, a long one leans, a stacked box is
    the smaller of its pair."""
    for _ in range(100):
        ids = [int(i) for i in rng.permutation([b.obj_id for b in BOXES])[: len(relations) + 1]]
        ok = "hide" not in relations or ids[0] in TALL  # the hiding box is the base, standing upright
        for j, rel in enumerate(relations, start=1):
            if rel == "hide":
                ok &= ids[j] in SMALL
            if rel == "slant":
                ok &= ids[j] in TALL
        if ok:
            return [BOX_BY_ID[i] for i in ids]
    raise RuntimeError(f"no boxes fit the relations {relations}")


def _parent_ok(rel: str, parent: Placed, child: Box) -> bool:
    """Can ``child`` be placed by ``rel`` against ``parent``? Parents rest flat on the table (not stacked or
    leaning); a hiding parent stands upright; a stacked child is the smaller box."""
    if parent.relation in ("stack", "slant"):
        return False
    if rel == "hide":
        return parent.box.obj_id in TALL and abs(parent.T[2, int(np.argmax(parent.box.extents))]) > 0.999
    if rel == "stack":
        return np.prod(child.extents) < np.prod(parent.box.extents)
    return True


def _base_pose(box: Box, relations: list[str], rng, lift: float) -> np.ndarray:
    """The first box: upright when a box is to hide behind it, on its largest face when one is stacked on it
    first (a broad support), else on a random face."""
    if "hide" in relations:
        up = int(np.argmax(box.extents))
    elif relations[0] == "stack":
        up = int(np.argmin(box.extents))
    else:
        up = int(rng.integers(3))
    R = resting_rotation(up, rng.uniform(-np.pi, np.pi), bool(rng.integers(2)))
    xy = rng.uniform(-0.05, 0.05, size=2)
    return make_pose(R, np.array([xy[0], xy[1], support_half_extent(R, box.extents, EZ) + lift]))


def draw_layout(sim: Sim, category: str, rng) -> tuple[list[Placed], list[np.ndarray]] | None:
    """Place boxes in ``sim`` by the category's relations (not yet settled). -> (layout, hide normals) or None."""
    relations = _draw_relations(category, rng)
    boxes = _draw_boxes(relations, rng)
    base = Placed(boxes[0], _base_pose(boxes[0], relations, rng, sim.cfg.lift))
    base.body = sim.add_box(base.box.extents, base.T)
    layout, hide_normals = [base], []
    for rel, box in zip(relations, boxes[1:]):
        parents = [i for i, p in enumerate(layout) if _parent_ok(rel, p, box)]
        if not parents:
            return None
        i_parent = parents[rng.integers(len(parents))]
        parent = layout[i_parent]
        body = sim.add_box(box.extents, make_pose(np.eye(3), [5.0, 5.0, 5.0]))  # parked far away until placed
        if rel == "touch":
            placed = place_touch(sim, rng, parent, box, body, edge=bool(rng.integers(2)))
            T = None if placed is None else placed[0]
        elif rel == "hide":
            placed = place_touch(sim, rng, parent, box, body, edge=False, hide=True)
            T = None if placed is None else placed[0]
            if placed is not None:
                hide_normals.append(placed[1])
        elif rel == "stack":
            T = place_stack(sim, rng, parent, box, body)
        else:
            T = place_slant(sim, rng, parent, box, body)
        if T is None:
            return None
        # The new box may touch only its partner (and the table): anything else makes an unplanned relation.
        if any(sim.distance(body, p.body) < 2 * sim.cfg.contact_tol for p in layout if p is not parent):
            return None
        layout.append(Placed(box, T, rel, i_parent, body))
    return layout, hide_normals


def relations_hold(sim: Sim, layout: list[Placed]) -> bool:
    """After settling: is every relation of the layout still true, and everything on the table?"""
    c = sim.cfg

    def flat(p: Placed) -> bool:
        return tilt_deg(p.T[:3, :3]) < c.flat_tol
    for p in layout:
        x, y, z = p.T[:3, 3]
        if abs(x) > c.table_size[0] / 2 - 0.02 or abs(y) > c.table_size[1] / 2 - 0.02 or z < 0:
            return False
        on_table = sim.touching(p.body, sim.table)
        if p.relation == "base":
            ok = on_table and flat(p)
        else:
            parent = layout[p.parent]
            ok = sim.touching(p.body, parent.body)
            if p.relation in ("touch", "hide"):
                ok = ok and on_table and flat(p) and flat(parent)
            elif p.relation == "stack":  # resting on the other box, not on the table
                ok = ok and not on_table and flat(p)
            elif p.relation == "slant":
                ok = ok and on_table and c.slant_range[0] <= tilt_deg(p.T[:3, :3]) <= c.slant_range[1]
        if not ok:
            return False
    return True


def settle_layout(sim: Sim, layout: list[Placed]) -> bool:
    """Simulate to rest and store the settled poses in the layout. False if it never came to rest."""
    ok = sim.settle([p.body for p in layout])
    for p in layout:
        p.T = sim.pose(p.body)
    return ok


def contact_distances(extents: np.ndarray, T_world_obj: np.ndarray, cfg: SynthConfig = SynthConfig()) -> np.ndarray:
    """Closest distances between boxes at given poses, for checking a scene read back from disk.

    ``extents``: (K, 3); ``T_world_obj``: (K, 4, 4). -> (K, K + 1) metres, column K the table, diagonal 0."""
    sim = Sim(cfg)
    try:
        sim.reset()
        bodies = [sim.add_box(e, T) for e, T in zip(extents, T_world_obj)]
        out = np.zeros((len(bodies), len(bodies) + 1))
        for i, a in enumerate(bodies):
            for j, b in enumerate(bodies + [sim.table]):
                if a != b:
                    out[i, j] = sim.distance(a, b)
        return out
    finally:
        sim.close()


# ----------------------------------------------------------------------------------------------------------------
# Rendering (open3d ray casting, full resolution)


def pixel_rays(K: np.ndarray, width: int, height: int, window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Rays from the camera centre through pixel centres (integer u, v in K's convention), camera frame.

    Directions have z = 1, so a hit distance is the depth. ``window``: (x0, y0, x1, y1) exclusive end.
    -> (h, w, 6) float32."""
    x0, y0, x1, y1 = (0, 0, width, height) if window is None else window
    u, v = np.meshgrid(np.arange(x0, x1), np.arange(y0, y1))
    rays = np.zeros(u.shape + (6,), dtype=np.float32)
    rays[..., 3] = (u - K[0, 2]) / K[0, 0]
    rays[..., 4] = (v - K[1, 2]) / K[1, 1]
    rays[..., 5] = 1.0
    return rays


def raycast(meshes: list[trimesh.Trimesh], rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hits of rays (.., 6) among meshes (same frame as the rays).

    -> (depth (..) float32 in units of the ray direction's length, 0 = nothing; index (..) int32 of the mesh hit,
    -1 = nothing)."""
    scene = o3d.t.geometry.RaycastingScene()
    ids = []
    for m in meshes:
        tm = o3d.t.geometry.TriangleMesh()
        tm.vertex.positions = o3d.core.Tensor(np.asarray(m.vertices, dtype=np.float32))
        tm.triangle.indices = o3d.core.Tensor(np.asarray(m.faces, dtype=np.int32))
        ids.append(scene.add_triangles(tm))
    hit = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32)))
    t = hit["t_hit"].numpy()
    gid = hit["geometry_ids"].numpy().astype(np.int64)
    lookup = np.full(max(ids) + 2, -1, dtype=np.int32)
    lookup[ids] = np.arange(len(ids))
    index = np.where(np.isfinite(t), lookup[np.minimum(gid, len(lookup) - 1)], -1).astype(np.int32)
    return np.where(np.isfinite(t), t, 0.0).astype(np.float32), index


def project(K: np.ndarray, p_cam: np.ndarray) -> np.ndarray:
    """Pixel coordinates of camera-frame points. (N, 3) -> (N, 2)."""
    return (p_cam[:, :2] / p_cam[:, 2:3]) * np.diag(K)[:2] + K[:2, 2]


def _window(K, width, height, mesh_cam: trimesh.Trimesh) -> tuple[int, int, int, int] | None:
    """Pixel box (x0, y0, x1, y1) holding a camera-frame mesh's projection; None if it is not in front."""
    v = np.asarray(mesh_cam.vertices)
    if np.any(v[:, 2] <= 1e-3):
        return None
    uv = project(K, v)
    x0, y0 = np.floor(uv.min(axis=0)).astype(int) - 1
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 2
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    return None if x0 >= x1 or y0 >= y1 else (x0, y0, x1, y1)


def masks_alone(K, width, height, meshes_cam: list[trimesh.Trimesh]) -> np.ndarray:
    """Each object's silhouette as if it were alone in view. -> (K, H, W) bool."""
    out = np.zeros((len(meshes_cam), height, width), dtype=bool)
    for k, m in enumerate(meshes_cam):
        win = _window(K, width, height, m)
        if win is None:
            continue
        _, idx = raycast([m], pixel_rays(K, width, height, win))
        out[k, win[1]:win[3], win[0]:win[2]] = idx == 0
    return out


def visible_masks(K: np.ndarray, width: int, height: int, meshes: list[trimesh.Trimesh],
                  T_cam_obj: np.ndarray) -> np.ndarray:
    """Visible pixels of each object among the others (no table: it hides nothing resting on it).

    ``meshes``: K model meshes (metres); ``T_cam_obj``: (K, 4, 4). -> (K, H, W) bool."""
    posed = [m.copy().apply_transform(T) for m, T in zip(meshes, T_cam_obj)]
    _, idx = raycast(posed, pixel_rays(K, width, height))
    return idx[None] == np.arange(len(meshes))[:, None, None]


def support_meshes(cfg: SynthConfig) -> list[trimesh.Trimesh]:
    """The table (top at z = 0) and a floor far below, in the table frame."""
    table = box_mesh([*cfg.table_size, cfg.table_thickness]).apply_translation([0, 0, -cfg.table_thickness / 2])
    floor = box_mesh([20.0, 20.0, 0.01]).apply_translation([0, 0, cfg.floor_z - 0.005])
    return [table, floor]


def render_clean(cfg: SynthConfig, T_cam_world: np.ndarray, layout: list[Placed]) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free depth of the table scene and which object each pixel shows.

    -> (depth (H, W) float32 metres, object index (H, W) int32: layout index, -1 for table/floor/nothing)."""
    world = support_meshes(cfg) + [box_mesh(p.box.extents).apply_transform(p.T) for p in layout]
    cam = [m.apply_transform(T_cam_world) for m in world]
    depth, idx = raycast(cam, pixel_rays(cfg.K(), cfg.width, cfg.height))
    return depth, np.where(idx >= 2, idx - 2, -1).astype(np.int32)


def draw_camera(cfg: SynthConfig, rng, layout: list[Placed], hide_normals: list[np.ndarray]) -> np.ndarray:
    """T_cam_world: 0.7-1.0 m from the table centre, 45-70 degrees up, looking at the boxes. With a hidden box the
    azimuth is drawn around the side opposite it, so that its tall partner stands in between."""
    if hide_normals:
        n = hide_normals[0]
        azimuth = np.arctan2(-n[1], -n[0]) + np.radians(rng.uniform(-1, 1) * cfg.hide_azimuth_jitter)
    else:
        azimuth = rng.uniform(-np.pi, np.pi)
    el = np.radians(rng.uniform(*cfg.cam_elevation))
    r = rng.uniform(*cfg.cam_distance)
    eye = r * np.array([np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth), np.sin(el)])
    target = np.mean([p.T[:3, 3] for p in layout], axis=0)
    return look_at(eye, target)


def _in_view(cfg: SynthConfig, T_cam_world: np.ndarray, layout: list[Placed]) -> bool:
    """Every box wholly inside the image."""
    K = cfg.K()
    for p in layout:
        v = box_mesh(p.box.extents).apply_transform(T_cam_world @ p.T).vertices
        if np.any(v[:, 2] <= 0.05):
            return False
        uv = project(K, np.asarray(v))
        if uv.min() < 0 or np.any(uv.max(axis=0) > [cfg.width - 1, cfg.height - 1]):
            return False
    return True


def _bbox(mask: np.ndarray) -> list[int]:
    """BOP bbox [x, y, w, h] of a mask; [-1, -1, 0, 0] when empty (as bop_toolkit)."""
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return [-1, -1, 0, 0]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]


# ----------------------------------------------------------------------------------------------------------------
# Whole scenes


@dataclass
class SceneSample:
    """One generated scene. Masks (K, H, W) follow ``layout``; depths (H, W) float32 metres."""

    category: str
    layout: list[Placed]
    T_cam_world: np.ndarray
    clean_depth: np.ndarray
    depth: np.ndarray
    mask_visib: np.ndarray
    mask_all: np.ndarray
    tries: int

    @property
    def visib_fract(self) -> np.ndarray:
        """(K,) visible pixels / pixels of the object rendered alone."""
        alone = self.mask_all.sum(axis=(1, 2))
        return np.where(alone > 0, self.mask_visib.sum(axis=(1, 2)) / np.maximum(alone, 1), 0.0)

    def gt_info(self) -> list[dict]:
        """scene_gt_info.json entries (bop_toolkit's fields)."""
        info = []
        for k in range(len(self.layout)):
            visib, alone = self.mask_visib[k], self.mask_all[k]
            info.append({
                "bbox_obj": _bbox(alone),
                "bbox_visib": _bbox(visib),
                "px_count_all": int(alone.sum()),
                "px_count_valid": int((alone & (self.depth > 0)).sum()),
                "px_count_visib": int(visib.sum()),
                "visib_fract": float(self.visib_fract[k]),
            })
        return info


def _views_ok(cfg: SynthConfig, layout: list[Placed], visib: np.ndarray) -> bool:
    hidden = np.array([p.relation == "hide" for p in layout])
    return bool(np.all(visib[hidden] < cfg.hidden_max_visib) and np.all(visib[~hidden] >= cfg.shown_min_visib))


def generate_scene(sim: Sim, category: str, rng: np.random.Generator, cfg: SynthConfig) -> SceneSample:
    """Draw layouts until one settles into what ``category`` says and a camera shows it so."""
    K = cfg.K()
    for tries in range(1, cfg.max_layout_tries + 1):
        sim.reset()
        drawn = draw_layout(sim, category, rng)
        if drawn is None:
            continue
        layout, hide_normals = drawn
        if not (settle_layout(sim, layout) and relations_hold(sim, layout)):
            continue
        for _ in range(cfg.max_camera_tries):
            T_cam_world = draw_camera(cfg, rng, layout, hide_normals)
            if not _in_view(cfg, T_cam_world, layout):
                continue
            clean, idx = render_clean(cfg, T_cam_world, layout)
            mask_visib = idx[None] == np.arange(len(layout))[:, None, None]
            cam_meshes = [box_mesh(p.box.extents).apply_transform(T_cam_world @ p.T) for p in layout]
            mask_all = masks_alone(K, cfg.width, cfg.height, cam_meshes)
            alone = mask_all.sum(axis=(1, 2))
            visib = mask_visib.sum(axis=(1, 2)) / np.maximum(alone, 1)
            if not _views_ok(cfg, layout, visib):
                continue
            depth = apply_sensor(clean, rng, cfg.sensor)
            return SceneSample(category, layout, T_cam_world, clean, depth, mask_visib, mask_all, tries)
    raise RuntimeError(f"no valid {category!r} scene in {cfg.max_layout_tries} layouts; loosen SynthConfig")


def _write_masks(folder: Path, im_id: int, masks: np.ndarray) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for k, m in enumerate(masks):
        Image.fromarray((m * 255).astype(np.uint8)).save(folder / f"{im_id:06d}_{k:06d}.png")


def write_scene(out: Path, scene_id: int, sample: SceneSample, cfg: SynthConfig, split: str = "test") -> None:
    """The sample as BOP frame ``im_id`` 0 of ``scene_id``, with mask and mask_visib PNGs."""
    gt = [(p.box.obj_id, sample.T_cam_world @ p.T) for p in sample.layout]
    bop.save_frame(out, scene_id, 0, sample.depth, cfg.K(), sample.T_cam_world, gt, sample.gt_info(), split=split)
    scene_dir = Path(out) / split / f"{scene_id:06d}"
    _write_masks(scene_dir / "mask_visib", 0, sample.mask_visib)
    _write_masks(scene_dir / "mask", 0, sample.mask_all)


def save_box_models(out: Path, obj_ids: list[int] | None = None) -> None:
    """The boxes' meshes and symmetries as BOP models."""
    boxes = [b for b in BOXES if obj_ids is None or b.obj_id in obj_ids]
    bop.save_models(
        out, {b.obj_id: box_mesh(b.extents) for b in boxes}, {b.obj_id: box_symmetries(b.extents) for b in boxes}
    )


def _write_camera_json(out: Path, cfg: SynthConfig) -> None:
    K = cfg.K()
    cam = {"cx": K[0, 2], "cy": K[1, 2], "fx": K[0, 0], "fy": K[1, 1], "width": cfg.width, "height": cfg.height,
           "depth_scale": 0.1}
    _write_json(Path(out) / "camera.json", cam)


def _write_json(path: Path, content: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(content, indent=2) + "\n")


def _scene_meta(scene_id: int, sample: SceneSample) -> dict:
    return {
        "scene_id": scene_id,
        "category": sample.category,
        "obj_ids": [p.box.obj_id for p in sample.layout],
        "relations": [[p.relation, p.parent] for p in sample.layout],
        "visib_fract": [round(float(v), 4) for v in sample.visib_fract],
        "tries": sample.tries,
    }


def check_out_folder(out: Path, force: bool) -> None:
    """A dataset is written into a new or empty folder: one that holds anything (another dataset, a user's files)
    is refused unless ``force``, because its frames and metadata would be replaced or merged."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "is a file: name a folder for the dataset")
    if out.is_dir() and not force and any(out.iterdir()):
        raise InputError(out, f"folder is not empty ({len(list(out.iterdir()))} entries): its files would be "
                              "replaced. Choose a new or empty folder, or pass --force to write into it")


def make_scenes(out: Path, categories: list[str], per_category: int, seed: int, width: int = 640,
                height: int = 480, force: bool = False) -> list[dict]:
    """Write ``per_category`` scenes of each category as a BOP dataset in ``out`` (split "test", one image each).

    Scene ids run over ``categories`` in order; each scene's random draw depends only on (seed, category,
    index within the category), so asking for fewer categories leaves the others' scenes unchanged.
    -> per scene {"scene_id", "category", "obj_ids", "relations", "visib_fract", "tries"} (also in scenes.json).
    ``out`` must be new or empty unless ``force``.
    """
    unknown = [c for c in categories if c not in CATEGORIES]
    if unknown:
        raise InputError("categories", f"unknown {unknown}; choose from {list(CATEGORIES)}")
    out = Path(out)
    check_out_folder(out, force)
    cfg = SynthConfig(width=width, height=height)
    save_box_models(out)
    _write_camera_json(out, cfg)
    meta = []
    sim = Sim(cfg)
    try:
        for category in categories:
            for j in range(per_category):
                rng = np.random.default_rng([seed, CATEGORIES.index(category), j])
                sample = generate_scene(sim, category, rng, cfg)
                write_scene(out, len(meta), sample, cfg)
                meta.append(_scene_meta(len(meta), sample))
    finally:
        sim.close()
    _write_json(out / "scenes.json", {"scenes": meta})
    return meta


def make_demo(out: Path, seed: int = 0, force: bool = False) -> list[dict]:
    """The bundled demo: two touching boxes on a table, one 640x480 frame (a few hundred kB). ``out`` must be new
    or empty unless ``force``."""
    out = Path(out)
    check_out_folder(out, force)
    cfg = SynthConfig()
    sim = Sim(cfg)
    try:
        sample = generate_scene(sim, "touching", np.random.default_rng([seed, CATEGORIES.index("touching"), 0]), cfg)
    finally:
        sim.close()
    ids = [p.box.obj_id for p in sample.layout]
    save_box_models(out, ids)
    _write_camera_json(out, cfg)
    write_scene(out, 0, sample, cfg)
    meta = [_scene_meta(0, sample)]
    _write_json(out / "scenes.json", {"scenes": meta})
    return meta
