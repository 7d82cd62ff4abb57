"""The Bullet world the projector simulates in: a table and one body per object, reused for every particle.

Determinism: a particle's result depends only on its own input, bit for bit, whatever the world simulated
before. Measured on pybullet 3.2.7, simply teleporting the bodies of a reused world gives results that differ from
a fresh world's by up to metres, because (1) a teleported body keeps the world inertia tensor of its previous
orientation until it is next integrated, (2) contact points survive a teleport, and (3) Bullet's default broadphase
(a dynamic AABB tree) keeps pairs of bodies that have parted and finds new pairs in an order that depends on its
history, which reorders the contact solver. So the world uses the simple broadphase, which drops a pair as soon
as the two boxes part and finds pairs in body order, and each particle starts by parking the bodies far apart at
their starting orientations and stepping once: that recomputes the inertia tensors and drops every pair and
contact. The world is then the same as a fresh one, for the cost of one step with no contacts (a few us; removing
and re-creating two bodies costs ~230 us, ``resetSimulation`` and re-creating everything ~1.2 ms).

pybullet's quaternion order (x, y, z, w) appears only in this module (the projector passes its quaternions on).
"""

from __future__ import annotations

import os
import shutil
import tempfile

import numpy as np
import trimesh

from workbench.errors import InputError
from workbench.geometry import invert_pose, make_pose, matrix_to_quat_wxyz, wxyz_to_xyzw
from workbench.physics.bodies import BodyFrame, body_frame, body_rotations, checked_masses, parking
from workbench.physics.bullet import pybullet
from workbench.physics.collision import BOX, COMPOUND, CYLINDER, CollisionShape
from workbench.physics.config import PhysicsConfig
from workbench.problem.scene import ObjectModel, Table


class World:
    """The table and the bodies of ``models`` (colliding as ``shapes``) in one pybullet DIRECT client.

    Construction is self-contained, so it can happen inside a spawned worker. Between particles the bodies wait
    parked far apart beside the table; ``place`` puts them where a particle starts, in the state of a fresh world
    (see the module doc). Attributes the projector simulates with: ``client``, ``bodies`` (Bullet ids, model
    order), ``frames`` (each body's ``BodyFrame``), ``sink`` (m, how far the table top lies below z = 0).
    """

    def __init__(self, models: list[ObjectModel], table: Table, config: PhysicsConfig,
                 shapes: list[CollisionShape]):
        masses = checked_masses(models, table, shapes)
        self.config = config
        self.shapes = list(shapes)
        self._models = list(models)
        self._table = table
        self._masses = masses
        self.frames = [body_frame(m.mesh, s, mass) for m, s, mass in zip(models, shapes, masses)]
        self._T_obj_body = np.stack([f.T_obj_body for f in self.frames]) if models else np.zeros((0, 4, 4))
        self._T_body_obj = invert_pose(self._T_obj_body)
        self._inertia = [f.inertia.tolist() for f in self.frames]
        self._parking = parking(self.frames, table.x_max, table.y_max)
        self._tmpdir = tempfile.mkdtemp(prefix="workbench_physics_")
        self.client = pybullet.connect(pybullet.DIRECT)
        try:
            self.build()
        except BaseException:
            self.close()
            raise

    def build(self) -> None:
        """Table and bodies, bodies parked far apart above the table until a particle places them. Called again
        after a blow-up, which may leave non-finite state (bodies, broadphase) behind."""
        cid, cfg, tb = self.client, self.config, self._table
        # The simple broadphase: see the module doc. Brute force over K + 1 bodies costs nothing here.
        pybullet.resetSimulation(pybullet.RESET_USE_SIMPLE_BROADPHASE, physicsClientId=cid)
        pybullet.setGravity(0.0, 0.0, -cfg.gravity, physicsClientId=cid)
        pybullet.setPhysicsEngineParameter(
            fixedTimeStep=cfg.timestep, numSolverIterations=cfg.solver_iterations, numSubSteps=0,
            solverResidualThreshold=cfg.solver_residual, enableConeFriction=int(cfg.cone_friction),
            physicsClientId=cid)
        half = [(tb.x_max - tb.x_min) / 2, (tb.y_max - tb.y_min) / 2, cfg.table_thickness / 2]
        table_shape = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half, physicsClientId=cid)
        self._table_centre = [(tb.x_min + tb.x_max) / 2, (tb.y_min + tb.y_max) / 2, -half[2]]
        self._table_body = pybullet.createMultiBody(0.0, table_shape, basePosition=self._table_centre,
                                                    physicsClientId=cid)
        self.sink = 0.0
        # Bullet combines rolling (and spinning) friction as r_a * f_b + r_b * f_a (f: lateral friction), so the
        # table has none of its own: an object's contact with it gets rolling_friction * table_friction.
        pybullet.changeDynamics(self._table_body, -1, lateralFriction=cfg.table_friction, rollingFriction=0.0,
                                spinningFriction=0.0, physicsClientId=cid)
        shape_ids = []
        for k, (model, shape, frame) in enumerate(zip(self._models, self.shapes, self.frames)):
            shape_id = self._create_shape(k, shape, frame)
            if shape_id < 0:
                raise InputError(model.source or f"model {model.obj_id}", "Bullet rejected its collision shape")
            shape_ids.append(shape_id)
        self.bodies = []
        for k, (model, shape_id, mass) in enumerate(zip(self._models, shape_ids, self._masses)):
            body = pybullet.createMultiBody(mass, shape_id, basePosition=self._parking[k].tolist(),
                                            useMaximalCoordinates=True, physicsClientId=cid)
            # Margin 0: Bullet otherwise pads hulls by 1 mm, so hull objects would rest 1 mm above the table.
            # Sleeping off: Bullet would freeze a body that has moved slowly (< 0.8 m/s) for 2 s, resting or not.
            pybullet.changeDynamics(
                body, -1, mass=mass, localInertiaDiagonal=self._inertia[k], lateralFriction=model.friction,
                rollingFriction=cfg.rolling_friction, spinningFriction=cfg.spinning_friction,
                linearDamping=cfg.linear_damping, angularDamping=cfg.angular_damping, collisionMargin=0.0,
                activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING, physicsClientId=cid)
            self.bodies.append(body)

    def _create_shape(self, k: int, shape: CollisionShape, frame: BodyFrame) -> int:
        cid = self.client
        T_body_shape = invert_pose(frame.T_obj_body) @ shape.T_obj_shape
        if shape.kind == BOX:
            # The body frame is the box frame, so the box needs no offset (an offset would wrap it in a compound).
            return pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=shape.half_extents.tolist(),
                                                 physicsClientId=cid)
        if shape.kind == CYLINDER:  # likewise; Bullet's cylinder axis is the body's z
            return pybullet.createCollisionShape(pybullet.GEOM_CYLINDER, radius=float(shape.half_extents[0]),
                                                 height=float(2.0 * shape.half_extents[2]), physicsClientId=cid)
        parts = [p @ T_body_shape[:3, :3].T + T_body_shape[:3, 3] for p in shape.parts]
        if shape.kind != COMPOUND:
            return pybullet.createCollisionShape(pybullet.GEOM_MESH, vertices=parts[0].tolist(), physicsClientId=cid)
        # pybullet builds a compound of convex hulls only from an OBJ file, one hull per "o" object.
        path = os.path.join(self._tmpdir, f"body{k}.obj")
        with open(path, "w") as f:
            offset = 1
            for i, part in enumerate(parts):
                hull = trimesh.convex.convex_hull(part)
                f.write(f"o part{i}\n")
                f.writelines(f"v {x:.17g} {y:.17g} {z:.17g}\n" for x, y, z in hull.vertices)
                f.writelines(f"f {a + offset} {b + offset} {c + offset}\n" for a, b, c in hull.faces)
                offset += len(hull.vertices)
        return pybullet.createCollisionShape(pybullet.GEOM_MESH, fileName=path, physicsClientId=cid)

    def close(self) -> None:
        if self.client is not None:
            pybullet.disconnect(physicsClientId=self.client)
            self.client = None
        shutil.rmtree(self._tmpdir, ignore_errors=True)

    def body_poses(self, T_world_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The bodies' poses for finite object poses (K, 4, 4): centres (K, 3), rotations (K, 3, 3) exactly
        orthonormal, as Bullet will use them, and those as quaternions (K, 4) xyzw. None when the poses'
        rotations are not rotations."""
        start = body_rotations(T_world_obj, self._T_obj_body)
        if start is None:
            return None
        pos, R = start
        quat = wxyz_to_xyzw(matrix_to_quat_wxyz(R))
        return pos, self._rotations(quat), quat

    def object_poses(self) -> np.ndarray:
        """Current object poses in the table frame -> (K, 4, 4)."""
        cid = self.client
        states = [pybullet.getBasePositionAndOrientation(body, physicsClientId=cid) for body in self.bodies]
        T_world_body = make_pose(self._rotations([q for _, q in states]), np.array([p for p, _ in states]))
        return T_world_body @ self._T_body_obj

    def set_sink(self, sink: float) -> None:
        """Put the table's top at z = -``sink`` (m); a static body moved between particles keeps no state."""
        if sink != self.sink:
            x, y, z = self._table_centre
            pybullet.resetBasePositionAndOrientation(self._table_body, [x, y, z - sink], [0.0, 0.0, 0.0, 1.0],
                                                     physicsClientId=self.client)
            self.sink = sink

    def place(self, pos: np.ndarray, quat: np.ndarray) -> None:
        """Put the bodies at rest at (K, 3) / (K, 4) xyzw with no state left from earlier particles: one step
        parked far apart at these orientations first (see the module doc). Bodies the previous particle put to sleep
        are woken (with Bullet's own sleeping off again)."""
        cid = self.client
        for body in self.bodies:
            pybullet.changeDynamics(body, -1, activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING,
                                    physicsClientId=cid)
        self.teleport(self._parking, quat)
        pybullet.stepSimulation(physicsClientId=self.client)
        self.teleport(pos, quat)

    def teleport(self, pos: np.ndarray, quat: np.ndarray) -> None:
        """Set the bodies' poses (K, 3) / (K, 4) xyzw, at rest."""
        cid, zero = self.client, [0.0, 0.0, 0.0]
        for k, body in enumerate(self.bodies):
            pybullet.resetBasePositionAndOrientation(body, pos[k].tolist(), quat[k].tolist(), physicsClientId=cid)
            pybullet.resetBaseVelocity(body, zero, zero, physicsClientId=cid)

    @staticmethod
    def _rotations(quat) -> np.ndarray:
        """xyzw quaternions (K, 4) -> rotations (K, 3, 3); pybullet's conversion, ~20x faster than numpy's for
        a handful of small arrays."""
        return np.array([pybullet.getMatrixFromQuaternion(q) for q in np.asarray(quat).tolist()]).reshape(-1, 3, 3)
