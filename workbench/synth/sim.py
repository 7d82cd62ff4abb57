"""The generator's own pybullet world (not the estimator's ``workbench.physics`` world, whose V-HACD
decomposition only it borrows for given models' pieces): a fixed table and free objects,
settled to rest, with contacts and closest distances for placing objects against each other and checking
relations. Given models collide as their convex hulls, or (``pieces``) as their V-HACD pieces (``bodies``); a
raised box the objects rest on is a fixed body like the table."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from workbench.geometry import (
    invert_pose,
    make_pose,
    matrix_to_quat_wxyz,
    quat_wxyz_to_matrix,
    wxyz_to_xyzw,
    xyzw_to_wxyz,
)
from workbench.physics.bullet import pybullet as pb
from workbench.synth.bodies import piece_body
from workbench.synth.config import SynthConfig
from workbench.synth.meshes import mug_collision_parts
from workbench.synth.objects import Box, Item, MeshItem, model_mesh


class Sim:
    """A pybullet DIRECT world with a fixed table (top at z = 0) and free boxes."""

    def __init__(self, cfg: SynthConfig):
        self.cfg = cfg
        self.cid = pb.connect(pb.DIRECT)
        self.table = -1
        self._T_obj_body: dict[int, np.ndarray] = {}  # bodies whose frame is not their object's (pieces)
        self._piece_files: dict[int, Path] = {}  # id(item) -> its pieces' OBJ file, written once per world
        self._tmpdir: Path | None = None

    def close(self) -> None:
        pb.disconnect(self.cid)
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)

    def reset(self) -> None:
        """Empty world with the table; bodies are re-created per scene (a reused world is not deterministic)."""
        c = self.cfg
        pb.resetSimulation(physicsClientId=self.cid)
        self._T_obj_body = {}
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

    def add_fixed_box(self, extents, T: np.ndarray) -> int:
        """A box that does not move (a raised support on the table), ``extents`` (3,) m at T_world_box (4, 4)."""
        half = (np.asarray(extents, dtype=np.float64) / 2).tolist()
        shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=self.cid)
        q = wxyz_to_xyzw(matrix_to_quat_wxyz(T[:3, :3]))
        body = pb.createMultiBody(0, shape, basePosition=T[:3, 3].tolist(), baseOrientation=q.tolist(),
                                  physicsClientId=self.cid)
        pb.changeDynamics(body, -1, lateralFriction=self.cfg.friction, restitution=0.0, physicsClientId=self.cid)
        return body

    def add_item(self, item: Item, T: np.ndarray, pieces: bool = False) -> int:
        """A free body of the object's shape: its box, a cylinder, (mug) a solid cylinder and handle boxes, or
        (a given mesh) its convex hull, or with ``pieces`` its V-HACD pieces (``bodies.piece_body``)."""
        if pieces and item.kind == "mesh":
            return self._add_pieces(item, T)
        if item.kind == "box":
            return self.add_box(item.extents, T)
        if item.kind == "can":
            shape = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=item.radius, height=item.height,
                                            physicsClientId=self.cid)
            return self._add_body(shape, float(np.pi * item.radius**2 * item.height), T)
        if item.kind == "mesh":  # its convex hull: all a body resting on the table, clear of the others, needs
            hull = model_mesh(item).convex_hull
            shape = pb.createCollisionShape(pb.GEOM_MESH, vertices=hull.vertices.tolist(), physicsClientId=self.cid)
            return self._add_body(shape, float(hull.volume), T)
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
        return self._add_body(shape, float(model_mesh(item).volume), T)

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

    def _add_pieces(self, item: MeshItem, T: np.ndarray) -> int:
        """A model as its pieces, its body frame at its centre of mass. Rolling and spinning friction as the
        estimator's physics has them (``PhysicsConfig``): without them a can on its side never comes to rest."""
        c, body_of = self.cfg, piece_body(item)
        if id(item) not in self._piece_files:
            if self._tmpdir is None:
                self._tmpdir = Path(tempfile.mkdtemp(prefix="workbench_synth_"))
            self._piece_files[id(item)] = self._tmpdir / f"pieces{len(self._piece_files)}.obj"
            body_of.write_obj(self._piece_files[id(item)])
        shape = pb.createCollisionShape(pb.GEOM_MESH, fileName=str(self._piece_files[id(item)]),
                                        physicsClientId=self.cid)
        mass = float(c.density * body_of.volume)
        body = pb.createMultiBody(mass, shape, useMaximalCoordinates=True, physicsClientId=self.cid)
        # Margin 0: Bullet otherwise pads hulls by a millimetre, and the objects would float above what they rest on.
        pb.changeDynamics(
            body, -1, mass=mass, localInertiaDiagonal=(mass * body_of.inertia).tolist(), lateralFriction=c.friction,
            rollingFriction=0.002, spinningFriction=0.002, restitution=0.0, linearDamping=0.04, angularDamping=0.04,
            collisionMargin=0.0, physicsClientId=self.cid)
        self._T_obj_body[body] = body_of.T_obj_body
        self.set_pose(body, T)
        return body

    def set_pose(self, body: int, T: np.ndarray) -> None:
        if body in self._T_obj_body:
            T = T @ self._T_obj_body[body]
        q = wxyz_to_xyzw(matrix_to_quat_wxyz(T[:3, :3]))
        pb.resetBasePositionAndOrientation(body, T[:3, 3].tolist(), q.tolist(), physicsClientId=self.cid)
        pb.resetBaseVelocity(body, [0, 0, 0], [0, 0, 0], physicsClientId=self.cid)

    def pose(self, body: int) -> np.ndarray:
        p, q = pb.getBasePositionAndOrientation(body, physicsClientId=self.cid)
        T = make_pose(quat_wxyz_to_matrix(xyzw_to_wxyz(np.asarray(q))), np.asarray(p))
        return T @ invert_pose(self._T_obj_body[body]) if body in self._T_obj_body else T

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
