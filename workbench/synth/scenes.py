"""Synthetic test scenes of the paper's cases and of real-like desks, written as a BOP dataset.

The paper's categories (Desingh et al. 2016, Sec. V), boxes on a bare 1.2 x 0.8 m table whose pose is given:
``touching`` (two boxes in face or edge contact), ``stacked`` (a smaller box resting on a larger one near its
edge), ``slant`` (a box leaning on another box and the table), ``occluded`` (a small box hidden behind a tall one),
``three`` and ``four`` (clutter mixing those relations).

Categories more like real frames (``DESKS``): ``clutter`` (4-6 objects, boxes with the can, the mug or both, some
touching, some stacked, the rest standing free, and 2-4 distractors; half the frames without the table pose) and
``mixed`` (2-3 objects mixing boxes with the can, the mug or both, 1-3 distractors, never the table pose). Their
desks are drawn from 0.9-2.4 x 0.7-1.5 m, often larger than the camera's view. *Distractors* are slabs (books), cylinders (cups,
bottles) and cables lying on the desk, clear of the objects: they are in the depth image but not in
scene_gt.json, from which the estimator learns which objects are present (scene_distractors.json lists them). A
frame without the table pose has no cam_R_w2c / cam_t_w2c in scene_camera.json, so the estimator must find the
table itself; the true pose is kept in scene_table.json. The can and the mug are meshes built here
(``meshes.py``), watertight, written with the boxes as BOP models (mm); the can is symmetric about its axis.

Every scene is laid out from *relations* (touch / stack / slant / hide / free), each new object moved along one
degree of freedom by bisection until it just touches its partner, then settled by physics in this module's own
pybullet world (independent of ``physics.py``) and kept only when the settled scene still is what its relations
say (contacts from ``getContactPoints``, tilt, visibility); otherwise the next random draw is tried. Distractors
are placed after settling, resting on the desk. Depth is ray-cast with open3d (independent of the estimator's
OpenGL renderer) and degraded by ``sensor.py``.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import ClassVar

import numpy as np
import open3d as o3d
import trimesh
from PIL import Image
from scipy.spatial import cKDTree

from workbench import bop
from workbench.geometry import (
    invert_pose, make_pose, matrix_to_quat_wxyz, quat_wxyz_to_matrix, rot_z, wxyz_to_xyzw, xyzw_to_wxyz,
)
from workbench.errors import InputError
from workbench.metrics import box_symmetries
from workbench.physics.bullet import pybullet as pb
from workbench.synth.meshes import MugShape, can_mesh, mug_collision_parts, mug_mesh, tube_mesh
from workbench.synth.sensor import SensorModel, apply_sensor

PAPER_CATEGORIES = ("touching", "stacked", "slant", "occluded", "three", "four")
CATEGORIES = PAPER_CATEGORIES + ("clutter", "mixed")  # new ones go last: a category's index seeds its scenes
EZ = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Box:
    obj_id: int
    name: str
    extents: tuple[float, float, float]  # metres, along the model's x, y, z
    kind: ClassVar[str] = "box"


@dataclass(frozen=True)
class Can:
    """A closed cylinder about the model's z axis, centred at its origin."""

    obj_id: int
    name: str
    radius: float
    height: float
    kind: ClassVar[str] = "can"

    @property
    def extents(self) -> tuple[float, float, float]:
        return (2 * self.radius, 2 * self.radius, self.height)


@dataclass(frozen=True)
class Mug:
    """A hollow cylinder with a handle along the model's +x (``meshes.MugShape``), centred on its bounding box."""

    obj_id: int
    name: str
    shape: MugShape = MugShape()
    kind: ClassVar[str] = "mug"

    @property
    def extents(self) -> tuple[float, float, float]:
        s = self.shape
        return (2 * s.radius + s.handle_reach + s.handle_thickness / 2, 2 * s.radius, s.height)


Item = Box | Can | Mug

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
# Round objects, generated here (YCB's tomato soup can and mug are about this size).
ROUND = (Can(7, "soup_can", 0.033, 0.101), Mug(8, "mug"))
OBJECTS = BOXES + ROUND
OBJECT_BY_ID = {o.obj_id: o for o in OBJECTS}


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
    distractor_clearance: float = 0.03  # seen from above, between a distractor and any object of interest
    sensor: SensorModel = field(default_factory=SensorModel)

    def K(self) -> np.ndarray:
        """Kinect-like intrinsics; principal point at the image centre (pixel centres at integer u, v)."""
        f = self.focal_640 * self.width / 640.0
        return np.array([[f, 0.0, (self.width - 1) / 2.0], [0.0, f, (self.height - 1) / 2.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class DeskSpec:
    """What a category adds to the paper's bare table to look like a real desk. Lengths metres."""

    distractors: tuple[int, int] = (0, 0)  # how many objects the estimator is not told about (inclusive range)
    table_pose: float = 1.0  # probability that scene_camera.json gives the table pose (cam_R_w2c, cam_t_w2c)
    table_size: tuple[tuple[float, float], tuple[float, float]] | None = None  # x, y ranges; None: SynthConfig's


# Desks up to 2.4 x 1.5 m: larger than the camera's view of them (about 1.2 x 0.9 m at 1 m).
LARGE_DESK = ((0.9, 2.4), (0.7, 1.5))
DESKS = {"clutter": DeskSpec((2, 4), 0.5, LARGE_DESK), "mixed": DeskSpec((1, 3), 0.0, LARGE_DESK)}


@dataclass
class Placed:
    """One object of a layout. ``relation``: how it was placed relative to ``parent`` (index into the layout;
    -1 for the base and for objects standing free)."""

    item: Item
    T: np.ndarray  # (4, 4) T_world_obj
    relation: str = "base"  # base | touch | stack | slant | hide | free
    parent: int = -1
    body: int = -1


# ----------------------------------------------------------------------------------------------------------------
# Geometry helpers


def box_mesh(extents) -> trimesh.Trimesh:
    """A box centred at its origin, metres."""
    return trimesh.creation.box(extents=np.asarray(extents, dtype=np.float64))


@functools.cache
def _model_mesh(item: Item) -> trimesh.Trimesh:
    if item.kind == "box":
        return box_mesh(item.extents)
    if item.kind == "can":
        return can_mesh(item.radius, item.height)
    return mug_mesh(item.shape)


def item_mesh(item: Item) -> trimesh.Trimesh:
    """The object's model mesh (metres, model frame): a fresh copy, free to transform."""
    return _model_mesh(item).copy()


def reach(item: Item, R: np.ndarray, direction: np.ndarray) -> float:
    """How far the object with rotation R (3, 3) extends from its origin along a unit world direction (3,)."""
    if item.kind == "box":  # exact and symmetric; kept in closed form so that box scenes stay bit for bit
        return support_half_extent(R, item.extents, direction)
    return float(np.max(_model_mesh(item).vertices @ (R.T @ direction)))


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
        e = np.asarray(extents, dtype=np.float64)
        shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=(e / 2).tolist(), physicsClientId=self.cid)
        return self._add_body(shape, float(np.prod(e)), T)

    def add_item(self, item: Item, T: np.ndarray) -> int:
        """A free body of the object's shape: its box, a cylinder, or (mug) a solid cylinder and handle boxes."""
        if item.kind == "box":
            return self.add_box(item.extents, T)
        if item.kind == "can":
            shape = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=item.radius, height=item.height,
                                            physicsClientId=self.cid)
            return self._add_body(shape, float(np.pi * item.radius**2 * item.height), T)
        parts = mug_collision_parts(item.shape)
        shape = pb.createCollisionShapeArray(
            [pb.GEOM_CYLINDER if kind == "cylinder" else pb.GEOM_BOX for kind, _, _ in parts],
            radii=[float(size[0]) for _, size, _ in parts],
            lengths=[float(size[1]) for _, size, _ in parts],
            halfExtents=[size.tolist() for _, size, _ in parts],
            collisionFramePositions=[P[:3, 3].tolist() for _, _, P in parts],
            collisionFrameOrientations=[wxyz_to_xyzw(matrix_to_quat_wxyz(P[:3, :3])).tolist() for _, _, P in parts],
            physicsClientId=self.cid,
        )
        return self._add_body(shape, float(_model_mesh(item).volume), T)

    def _add_body(self, shape: int, volume: float, T: np.ndarray) -> int:
        c = self.cfg
        body = pb.createMultiBody(
            float(c.density * volume), shape, useMaximalCoordinates=True, physicsClientId=self.cid
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


def side_normals(p: Placed) -> list[np.ndarray]:
    """Horizontal directions (world, unit) to place a neighbour along: a box's four side faces; all around a
    round object, eight directions turned with it."""
    if p.item.kind == "box":
        return horizontal_faces(p.T[:3, :3])
    yaw = np.arctan2(p.T[1, 0], p.T[0, 0])
    return [np.array([np.cos(a), np.sin(a), 0.0]) for a in yaw + np.arange(8) * np.pi / 4]


def place_touch(sim: Sim, rng, parent: Placed, box: Item, body: int, edge: bool, hide: bool = False):
    """``box`` on the table against a side face of ``parent``: face to face, or (``edge``) turned so that a
    vertical edge meets the face. ``hide``: lying flat, aligned and centred on the face, to be hidden behind it.
    A round object stands upright, turned at random. -> (T_world_obj, outward normal of the parent's face) or
    None."""
    c_A, R_A = parent.T[:3, 3], parent.T[:3, :3]
    faces = side_normals(parent)
    n = faces[rng.integers(len(faces))]
    t = np.cross(EZ, n)
    up = int(np.argmin(box.extents)) if hide else int(rng.integers(3))
    yaw_A = np.arctan2(n[1], n[0])
    yaw = yaw_A + rng.integers(4) * np.pi / 2 + (rng.uniform(np.radians(20), np.radians(70)) if edge else 0.0)
    R = resting_rotation(up, yaw, bool(rng.integers(2)))
    if box.kind != "box":
        R = rot_z(yaw)
    hA_n = reach(parent.item, R_A, n)
    hA_t = reach(parent.item, R_A, t)
    hB_n = reach(box, R, -n)
    hB_t = reach(box, R, t)
    if hide:
        room = max(hA_t - hB_t, 0.0)
        lateral = rng.uniform(-room, room) * 0.5
    else:
        lateral = rng.uniform(-0.6, 0.6) * hA_t
    z = reach(box, R, -EZ) + sim.cfg.lift

    def pose_at(s: float) -> np.ndarray:
        p = c_A + n * s + t * lateral
        return make_pose(R, np.array([p[0], p[1], z]))

    T = bisect_contact(sim, body, parent.body, pose_at, hA_n + hB_n + 0.05, hA_n + hB_n - 0.01)
    return None if T is None else (T, n)


def place_stack(sim: Sim, rng, parent: Placed, box: Item, body: int):
    """``box`` lowered onto the top of box ``parent``, its centre out towards one edge (it may overhang). A round
    object stands upright."""
    c_A, R_A = parent.T[:3, 3], parent.T[:3, :3]
    faces = horizontal_faces(R_A)
    n = faces[rng.integers(len(faces))]
    t = np.cross(EZ, n)
    up = int(rng.integers(3))
    R = resting_rotation(up, np.arctan2(n[1], n[0]) + rng.uniform(-np.pi, np.pi), bool(rng.integers(2)))
    if box.kind != "box":
        R = rot_z(np.arctan2(R[1, 0], R[0, 0]))
    hA_n = reach(parent.item, R_A, n)
    hA_t = reach(parent.item, R_A, t)
    top = c_A[2] + reach(parent.item, R_A, EZ)
    hB_z = reach(box, R, -EZ)
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
    H_A = c_A[2] + support_half_extent(R_A, parent.item.extents, EZ)
    theta = np.radians(rng.uniform(15.0, 45.0))
    # Pivot distance from the parent's face for the intended lean: the top corner meets the face when the parent is
    # taller than the leaning box's top, else the leaning face rests on the parent's top edge.
    D = h * np.sin(theta) if h * np.cos(theta) <= H_A else H_A * np.tan(theta)
    face = c_A + n * support_half_extent(R_A, parent.item.extents, n)
    pivot = face + n * D + t * rng.uniform(-0.4, 0.4) * support_half_extent(R_A, parent.item.extents, t)
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
    """The relations (besides the base object) a scene of ``category`` is built from."""
    single = {"touching": "touch", "stacked": "stack", "slant": "slant", "occluded": "hide"}
    if category in single:
        return [single[category]]
    if category == "clutter":  # 4-6 objects, some touching and some stacked, the rest standing free
        n = int(rng.integers(3, 6))
        while True:
            rel = [str(r) for r in rng.choice(["touch", "stack", "free"], size=n)]
            if "touch" in rel and "stack" in rel:
                return rel
    if category == "mixed":  # 2-3 objects, boxes and round ones, in any relation
        return [str(r) for r in rng.choice(["touch", "stack", "free"], size=int(rng.integers(1, 3)))]
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


def _draw_items(category: str, relations: list[str], rng) -> list[Item]:
    """Distinct objects for the relations. ``clutter`` and ``mixed`` draw from the boxes and the round objects,
    at least one of each, with a box as the base; the paper's categories use boxes only (:func:`_draw_boxes`)."""
    if category not in ("clutter", "mixed"):
        return _draw_boxes(relations, rng)
    while True:
        ids = [int(i) for i in rng.permutation([o.obj_id for o in OBJECTS])[: len(relations) + 1]]
        items = [OBJECT_BY_ID[i] for i in ids]
        if items[0].kind == "box" and any(o.kind != "box" for o in items):
            return items


def _parent_ok(rel: str, parent: Placed, child: Item) -> bool:
    """Can ``child`` be placed by ``rel`` against ``parent``? Parents rest flat on the table (not stacked or
    leaning); a hiding parent stands upright; a stacked child is the smaller one, on a box."""
    if parent.relation in ("stack", "slant"):
        return False
    if rel == "hide":
        return parent.item.obj_id in TALL and abs(parent.T[2, int(np.argmax(parent.item.extents))]) > 0.999
    if rel == "stack":
        return parent.item.kind == "box" and np.prod(child.extents) < np.prod(parent.item.extents)
    if rel == "slant":
        return parent.item.kind == "box"
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


def place_free(sim: Sim, rng, layout: list[Placed], item: Item, body: int, clearance: float = 0.02):
    """``item`` standing on the table 10-25 cm from the layout's centre, at least ``clearance`` from everything
    (a box on a random face, a round object upright). -> T_world_obj or None."""
    centre = np.mean([p.T[:3, 3] for p in layout], axis=0)
    for _ in range(20):
        yaw = rng.uniform(-np.pi, np.pi)
        R = resting_rotation(int(rng.integers(3)), yaw, bool(rng.integers(2))) if item.kind == "box" else rot_z(yaw)
        a, r = rng.uniform(-np.pi, np.pi), rng.uniform(0.10, 0.25)
        T = make_pose(R, np.array([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a),
                                   reach(item, R, -EZ) + sim.cfg.lift]))
        sim.set_pose(body, T)
        if all(sim.distance(body, p.body) > clearance for p in layout):
            return T
    return None


def draw_layout(sim: Sim, category: str, rng) -> tuple[list[Placed], list[np.ndarray]] | None:
    """Place objects in ``sim`` by the category's relations (not yet settled). -> (layout, hide normals) or None."""
    relations = _draw_relations(category, rng)
    items = _draw_items(category, relations, rng)
    base = Placed(items[0], _base_pose(items[0], relations, rng, sim.cfg.lift))
    base.body = sim.add_item(base.item, base.T)
    layout, hide_normals = [base], []
    for rel, item in zip(relations, items[1:]):
        body = sim.add_item(item, make_pose(np.eye(3), [5.0, 5.0, 5.0]))  # parked far away until placed
        if rel == "free":
            T = place_free(sim, rng, layout, item, body)
            if T is None:
                return None
            layout.append(Placed(item, T, rel, -1, body))
            continue
        parents = [i for i, p in enumerate(layout) if _parent_ok(rel, p, item)]
        if not parents:
            return None
        i_parent = parents[rng.integers(len(parents))]
        parent = layout[i_parent]
        if rel == "touch":
            placed = place_touch(sim, rng, parent, item, body, edge=bool(rng.integers(2)))
            T = None if placed is None else placed[0]
        elif rel == "hide":
            placed = place_touch(sim, rng, parent, item, body, edge=False, hide=True)
            T = None if placed is None else placed[0]
            if placed is not None:
                hide_normals.append(placed[1])
        elif rel == "stack":
            T = place_stack(sim, rng, parent, item, body)
        else:
            T = place_slant(sim, rng, parent, item, body)
        if T is None:
            return None
        # The new object may touch only its partner (and the table): anything else makes an unplanned relation.
        if any(sim.distance(body, p.body) < 2 * sim.cfg.contact_tol for p in layout if p is not parent):
            return None
        layout.append(Placed(item, T, rel, i_parent, body))
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
        if p.relation in ("base", "free"):
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
    return item_distances([Box(0, "box", tuple(e)) for e in np.asarray(extents, dtype=np.float64)], T_world_obj, cfg)


def item_distances(items: list[Item], T_world_obj: np.ndarray, cfg: SynthConfig = SynthConfig()) -> np.ndarray:
    """Closest distances between objects (their collision shapes here) at given poses. ``T_world_obj``: (K, 4, 4).
    -> (K, K + 1) metres, column K the table, diagonal 0."""
    sim = Sim(cfg)
    try:
        sim.reset()
        bodies = [sim.add_item(o, T) for o, T in zip(items, T_world_obj)]
        out = np.zeros((len(bodies), len(bodies) + 1))
        for i, a in enumerate(bodies):
            for j, b in enumerate(bodies + [sim.table]):
                if a != b:
                    out[i, j] = sim.distance(a, b)
        return out
    finally:
        sim.close()


# ----------------------------------------------------------------------------------------------------------------
# Distractors: things on the desk the estimator is not told about


@dataclass
class Distractor:
    """A slab (book, notepad), a cylinder (cup, bottle) or a cable lying on the table.

    ``params`` (metres): slab {"extents"}, cylinder {"radius", "height"}, cable {"radius", "path" (P, 3) in the
    model frame}. ``T``: (4, 4) T_world_obj, the model resting on z = 0."""

    kind: str
    params: dict
    T: np.ndarray

    def mesh(self) -> trimesh.Trimesh:
        """Model-frame mesh (metres)."""
        return distractor_mesh(self.kind, self.params)


DISTRACTOR_KINDS = ("slab", "cylinder", "cable")


def distractor_mesh(kind: str, params: dict) -> trimesh.Trimesh:
    """A distractor's mesh in its model frame (centred; the cable along its path). Metres."""
    if kind == "slab":
        return box_mesh(params["extents"])
    if kind == "cylinder":
        return can_mesh(params["radius"], params["height"], sections=32)
    return tube_mesh(np.asarray(params["path"]), params["radius"])


def draw_distractor(rng) -> tuple[str, dict]:
    """The shape of one distractor: sizes of books, cups and bottles, cables 25-70 cm long."""
    kind = DISTRACTOR_KINDS[int(rng.integers(len(DISTRACTOR_KINDS)))]
    if kind == "slab":
        return kind, {"extents": [rng.uniform(0.10, 0.30), rng.uniform(0.07, 0.22), rng.uniform(0.004, 0.04)]}
    if kind == "cylinder":
        return kind, {"radius": rng.uniform(0.015, 0.045), "height": rng.uniform(0.03, 0.22)}
    radius, steps = rng.uniform(0.002, 0.005), int(rng.uniform(25, 70))
    heading = np.cumsum(rng.normal(0.0, 0.15, size=steps)) + rng.uniform(-np.pi, np.pi)  # 1 cm steps, bending
    path = np.cumsum(0.01 * np.stack([np.cos(heading), np.sin(heading), np.zeros(steps)], axis=-1), axis=0)
    return kind, {"radius": radius, "path": (path - path.mean(axis=0)).tolist()}


def _footprint(mesh_world: trimesh.Trimesh, n: int = 400) -> np.ndarray:
    """Points covering a posed mesh, seen from above: vertices and surface samples, xy. -> (N, 2)."""
    samples, _ = trimesh.sample.sample_surface(mesh_world, n, seed=0)
    return np.concatenate([np.asarray(mesh_world.vertices), samples])[:, :2]


def place_distractors(rng, layout: list[Placed], count: int, cfg: SynthConfig) -> list[Distractor]:
    """Up to ``count`` distractors resting on the table 10-45 cm from the objects' centre, each at least
    ``cfg.distractor_clearance`` (seen from above) from every object, so that no relation changes, and clear of
    one another and of the table's edge. Static: they rest on the table by construction."""
    objects = np.concatenate([_footprint(item_mesh(p.item).apply_transform(p.T)) for p in layout])
    tree = cKDTree(objects)
    centre = objects.mean(axis=0)
    half = np.array(cfg.table_size) / 2 - 0.02
    placed, taken = [], np.zeros((0, 2))
    for _ in range(count):
        for _ in range(30):
            kind, params = draw_distractor(rng)
            mesh = distractor_mesh(kind, params)
            a, r = rng.uniform(-np.pi, np.pi), rng.uniform(0.10, 0.45)
            xy = centre + r * np.array([np.cos(a), np.sin(a)])
            T = make_pose(rot_z(rng.uniform(-np.pi, np.pi)), np.array([xy[0], xy[1], -mesh.bounds[0, 2]]))
            pts = _footprint(mesh.apply_transform(T))
            if np.any(np.abs(pts) > half) or tree.query(pts)[0].min() < cfg.distractor_clearance:
                continue
            if len(taken) and cKDTree(taken).query(pts)[0].min() < 0.01:
                continue
            placed.append(Distractor(kind, params, T))
            taken = np.concatenate([taken, pts])
            break
    return placed


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


def render_clean(cfg: SynthConfig, T_cam_world: np.ndarray, layout: list[Placed],
                 distractors: list[Distractor] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free depth of the table scene and which object each pixel shows.

    -> (depth (H, W) float32 metres, object index (H, W) int32: layout index, -1 for table, floor, distractors
    and nothing)."""
    world = support_meshes(cfg) + [item_mesh(p.item).apply_transform(p.T) for p in layout]
    world += [d.mesh().apply_transform(d.T) for d in distractors]
    cam = [m.apply_transform(T_cam_world) for m in world]
    depth, idx = raycast(cam, pixel_rays(cfg.K(), cfg.width, cfg.height))
    return depth, np.where((idx >= 2) & (idx < 2 + len(layout)), idx - 2, -1).astype(np.int32)


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
    """Every object wholly inside the image (distractors may be cut by its border)."""
    K = cfg.K()
    for p in layout:
        v = item_mesh(p.item).apply_transform(T_cam_world @ p.T).vertices
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
    distractors: list[Distractor] = field(default_factory=list)
    table_pose: bool = True  # whether scene_camera.json gives the table pose
    table_size: tuple[float, float] = SynthConfig.table_size

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


def _draw_desk(desk: DeskSpec, cfg: SynthConfig, rng) -> SynthConfig:
    """The scene's configuration with its table size drawn (``cfg`` itself when the desk keeps the default)."""
    if desk.table_size is None:
        return cfg
    (x0, x1), (y0, y1) = desk.table_size
    return replace(cfg, table_size=(float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1))))


def generate_scene(sim: Sim, category: str, rng: np.random.Generator, cfg: SynthConfig,
                   desk: DeskSpec | None = None) -> SceneSample:
    """Draw layouts until one settles into what ``category`` says and a camera shows it so. ``desk``: table size,
    distractors and table pose (default: the category's, ``DESKS``)."""
    desk = DESKS.get(category, DeskSpec()) if desk is None else desk
    cfg = _draw_desk(desk, cfg, rng)
    sim.cfg = cfg
    K = cfg.K()
    for tries in range(1, cfg.max_layout_tries + 1):
        sim.reset()
        drawn = draw_layout(sim, category, rng)
        if drawn is None:
            continue
        layout, hide_normals = drawn
        if not (settle_layout(sim, layout) and relations_hold(sim, layout)):
            continue
        lo, hi = desk.distractors
        distractors = place_distractors(rng, layout, int(rng.integers(lo, hi + 1)), cfg) if hi > 0 else []
        for _ in range(cfg.max_camera_tries):
            T_cam_world = draw_camera(cfg, rng, layout, hide_normals)
            if not _in_view(cfg, T_cam_world, layout):
                continue
            clean, idx = render_clean(cfg, T_cam_world, layout, distractors)
            mask_visib = idx[None] == np.arange(len(layout))[:, None, None]
            cam_meshes = [item_mesh(p.item).apply_transform(T_cam_world @ p.T) for p in layout]
            mask_all = masks_alone(K, cfg.width, cfg.height, cam_meshes)
            alone = mask_all.sum(axis=(1, 2))
            visib = mask_visib.sum(axis=(1, 2)) / np.maximum(alone, 1)
            if not _views_ok(cfg, layout, visib):
                continue
            depth = apply_sensor(clean, rng, cfg.sensor)
            table_pose = bool(rng.random() < desk.table_pose) if 0.0 < desk.table_pose < 1.0 else desk.table_pose >= 1
            return SceneSample(category, layout, T_cam_world, clean, depth, mask_visib, mask_all, tries,
                               distractors, table_pose, cfg.table_size)
    raise RuntimeError(f"no valid {category!r} scene in {cfg.max_layout_tries} layouts; loosen SynthConfig")


def _write_masks(folder: Path, im_id: int, masks: np.ndarray) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for k, m in enumerate(masks):
        Image.fromarray((m * 255).astype(np.uint8)).save(folder / f"{im_id:06d}_{k:06d}.png")


def write_scene(out: Path, scene_id: int, sample: SceneSample, cfg: SynthConfig, split: str = "test") -> None:
    """The sample as BOP frame ``im_id`` 0 of ``scene_id``, with mask and mask_visib PNGs.

    Only the objects of interest go into scene_gt.json (the estimator reads from it which objects are present).
    Distractors, if any, are listed in scene_distractors.json; a table pose left out of scene_camera.json is
    kept in scene_table.json, both for reference and scoring (:func:`load_distractors`, :func:`true_table_pose`).
    """
    gt = [(p.item.obj_id, sample.T_cam_world @ p.T) for p in sample.layout]
    T_given = sample.T_cam_world if sample.table_pose else None
    bop.save_frame(out, scene_id, 0, sample.depth, cfg.K(), T_given, gt, sample.gt_info(), split=split)
    scene_dir = Path(out) / split / f"{scene_id:06d}"
    _write_masks(scene_dir / "mask_visib", 0, sample.mask_visib)
    _write_masks(scene_dir / "mask", 0, sample.mask_all)
    if not sample.table_pose:
        R, t = sample.T_cam_world[:3, :3], sample.T_cam_world[:3, 3] / bop.MM
        table = {"cam_R_w2c": R.ravel().tolist(), "cam_t_w2c": t.tolist(),
                 "table_size": [v / bop.MM for v in sample.table_size]}
        _write_json(scene_dir / "scene_table.json", {"0": table})
    if sample.distractors:
        _write_json(scene_dir / "scene_distractors.json",
                    {"0": [_distractor_entry(d, sample.T_cam_world) for d in sample.distractors]})


def _distractor_entry(d: Distractor, T_cam_world: np.ndarray) -> dict:
    """A distractor as JSON: kind, sizes in mm, pose in the camera frame (BOP's cam_R_m2c, cam_t_m2c)."""
    T = T_cam_world @ d.T
    params = {k: (np.asarray(v) / bop.MM).tolist() for k, v in d.params.items()}
    return {"kind": d.kind, **{f"{k}_mm": v for k, v in params.items()},
            "cam_R_m2c": T[:3, :3].ravel().tolist(), "cam_t_m2c": (T[:3, 3] / bop.MM).tolist()}


def load_distractors(dataset: Path, scene_id: int, im_id: int = 0,
                     split: str = "test") -> list[tuple[trimesh.Trimesh, np.ndarray]]:
    """The distractors of a generated frame: (model mesh in metres, T_cam_obj (4, 4) metres) each; [] if none."""
    path = Path(dataset) / split / f"{scene_id:06d}" / "scene_distractors.json"
    if not path.is_file():
        return []
    out = []
    for e in bop.read_json(path).get(str(im_id), []):
        params = {k[:-3]: np.asarray(v) * bop.MM for k, v in e.items() if k.endswith("_mm")}
        T = bop.parse_pose(e["cam_R_m2c"], e["cam_t_m2c"], path, f"image {im_id} distractor")
        out.append((distractor_mesh(e["kind"], params), T))
    return out


def true_table_pose(dataset: Path, scene_id: int, im_id: int = 0, split: str = "test") -> np.ndarray:
    """T_cam_world (4, 4, metres) of a generated frame: from scene_camera.json, else from scene_table.json."""
    return _table_pose_in(Path(dataset) / split / f"{scene_id:06d}", im_id)


def frame_table_pose(frame) -> np.ndarray:
    """The true T_cam_world (4, 4) of a loaded generated ``Frame``: its camera's, else its scene's
    scene_table.json (found next to its depth image), for scoring frames that do not give it."""
    if frame.camera.T_cam_world is not None:
        return frame.camera.T_cam_world
    return _table_pose_in(Path(frame.source).parent.parent, frame.im_id)


def _table_pose_in(scene_dir: Path, im_id: int) -> np.ndarray:
    for name in ("scene_camera.json", "scene_table.json"):
        path = scene_dir / name
        entry = bop.read_json(path).get(str(im_id), {}) if path.is_file() else {}
        if "cam_R_w2c" in entry:
            return bop.parse_pose(entry["cam_R_w2c"], entry["cam_t_w2c"], path, f"image {im_id} table pose")
    raise InputError(scene_dir, f"image {im_id}: no table pose in scene_camera.json or scene_table.json")


def save_box_models(out: Path, obj_ids: list[int] | None = None) -> None:
    """The boxes' meshes and symmetries as BOP models."""
    boxes = [b for b in BOXES if obj_ids is None or b.obj_id in obj_ids]
    bop.save_models(
        out, {b.obj_id: box_mesh(b.extents) for b in boxes}, {b.obj_id: box_symmetries(b.extents) for b in boxes}
    )


def save_object_models(out: Path) -> None:
    """Every object's mesh as a BOP model: the boxes with their discrete symmetries, the can with its continuous
    one about z (and the flip end over end), the mug with none (its handle breaks every symmetry)."""
    save_box_models(out)
    can, mug = ROUND
    flip = make_pose(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
    bop.save_models(out, {can.obj_id: item_mesh(can), mug.obj_id: item_mesh(mug)}, {can.obj_id: flip[None]},
                    symmetries_continuous={can.obj_id: [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]})


def _write_camera_json(out: Path, cfg: SynthConfig) -> None:
    K = cfg.K()
    cam = {"cx": K[0, 2], "cy": K[1, 2], "fx": K[0, 0], "fy": K[1, 1], "width": cfg.width, "height": cfg.height,
           "depth_scale": 0.1}
    _write_json(Path(out) / "camera.json", cam)


def _write_json(path: Path, content: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(content, indent=2) + "\n")


def _scene_meta(scene_id: int, sample: SceneSample) -> dict:
    meta = {
        "scene_id": scene_id,
        "category": sample.category,
        "obj_ids": [p.item.obj_id for p in sample.layout],
        "relations": [[p.relation, p.parent] for p in sample.layout],
        "visib_fract": [round(float(v), 4) for v in sample.visib_fract],
        "tries": sample.tries,
    }
    # Only where a scene differs from the paper's set-up (absent: 1.2 x 0.8 m table, pose given, no distractors).
    if sample.table_size != SynthConfig.table_size:
        meta["table_size"] = [round(v, 4) for v in sample.table_size]
    if not sample.table_pose:
        meta["table_pose"] = False
    if sample.distractors:
        meta["distractors"] = [d.kind for d in sample.distractors]
    return meta


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
                height: int = 480, distractors: int | None = None, table_pose: float | None = None,
                force: bool = False) -> list[dict]:
    """Write ``per_category`` scenes of each category as a BOP dataset in ``out`` (split "test", one image each).

    Scene ids run over ``categories`` in order; each scene's random draw depends only on (seed, category,
    index within the category), so asking for fewer categories leaves the others' scenes unchanged.
    ``distractors`` (a count per scene) and ``table_pose`` (the probability that a frame's scene_camera.json
    gives the table pose) override every category's ``DESKS`` entry.
    -> per scene {"scene_id", "category", "obj_ids", "relations", "visib_fract", "tries"} and, where they differ
    from the paper's set-up, "table_size", "table_pose", "distractors" (also in scenes.json).
    ``out`` must be new or empty unless ``force``.
    """
    unknown = [c for c in categories if c not in CATEGORIES]
    if unknown:
        raise InputError("categories", f"unknown {unknown}; choose from {list(CATEGORIES)}")
    if distractors is not None and distractors < 0:
        raise InputError("distractors", f"must be >= 0, got {distractors}")
    if table_pose is not None and not 0.0 <= table_pose <= 1.0:
        raise InputError("table pose", f"the share of frames that give it must be in [0, 1], got {table_pose}")
    out = Path(out)
    check_out_folder(out, force)
    cfg = SynthConfig(width=width, height=height)
    save_object_models(out)
    _write_camera_json(out, cfg)
    meta = []
    sim = Sim(cfg)
    try:
        for category in categories:
            desk = DESKS.get(category, DeskSpec())
            if distractors is not None:
                desk = replace(desk, distractors=(distractors, distractors))
            if table_pose is not None:
                desk = replace(desk, table_pose=table_pose)
            for j in range(per_category):
                rng = np.random.default_rng([seed, CATEGORIES.index(category), j])
                sample = generate_scene(sim, category, rng, cfg, desk)
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
    ids = [p.item.obj_id for p in sample.layout]
    save_box_models(out, ids)
    _write_camera_json(out, cfg)
    write_scene(out, 0, sample, cfg)
    meta = [_scene_meta(0, sample)]
    _write_json(out / "scenes.json", {"scenes": meta})
    return meta
