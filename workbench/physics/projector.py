"""Physics projection (PI-PF): simulate a hypothesis until it is at rest; the resting poses are its projection.

A hypothesis is the poses of the K objects in the table frame. ``PhysicsProjector.project`` pushes the objects out
of the table and out of each other, lets them fall and settle under gravity in Bullet (pybullet), and returns where
they came to rest.

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

pybullet's quaternion order (x, y, z, w) appears only in this module.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from dataclasses import dataclass

import numpy as np
import trimesh

from workbench.errors import InputError
from workbench.geometry import invert_pose, make_pose, matrix_to_quat_wxyz, wxyz_to_xyzw
from workbench.physics.bullet import pybullet
from workbench.physics.collision import BOX, COMPOUND, CYLINDER, KINDS, CollisionShape, collision_shape_for
from workbench.scene import ObjectModel, Table

STATUS_REST, STATUS_STEP_CAP, STATUS_UNSTABLE, STATUS_OFF_TABLE = 0, 1, 2, 3
# Set by the evaluator, not here: at rest, but an object's centre lies outside the region where objects are seen.
STATUS_OUTSIDE = 4
# Set by the evaluator: scored as given, not simulated (``Evaluator.evaluate(..., project=False)``).
STATUS_AS_GIVEN = 5
STATUS_NAMES = {STATUS_REST: "rest", STATUS_STEP_CAP: "step cap", STATUS_UNSTABLE: "unstable",
                STATUS_OFF_TABLE: "off the table", STATUS_OUTSIDE: "outside the object region",
                STATUS_AS_GIVEN: "as given, not simulated"}


@dataclass(frozen=True)
class PhysicsConfig:
    """How a hypothesis is simulated to rest. Defaults chosen by measurement (benchmarks/physics_speed.py).

    The particle is at rest when every object's speeds stay below ``rest_linear`` (m/s) and ``rest_angular``
    (rad/s) at ``rest_checks`` consecutive checks, made every ``check_every`` steps. An object whose centre of mass
    drops below ``off_table_z`` has fallen off the table; a speed above ``max_speed`` (m/s) or ``max_angular``
    (rad/s), or a centre more than ``max_distance`` beyond the table's edges or above it, means the simulation blew
    up. Before simulating, penetrations deeper than ``penetration_tolerance`` are pushed apart in up to
    ``separation_iterations`` passes. ``table_friction`` multiplies each object's own friction: Bullet's combined
    friction is the product of the two. ``rolling_friction`` (m) and ``spinning_friction`` (m) of the objects
    resist rolling and turning in place (Bullet limits the contact torque to about them times the normal force,
    combined as r_a * f_b + r_b * f_a with the lateral frictions f): without them a can or marker on its side
    rolls on for as long as it is simulated.
    ``linear_damping`` and ``angular_damping`` are Bullet's velocity damping (the fraction of speed lost per
    second). ``solver_residual``: the contact solver stops iterating below it; ``cone_friction``: Bullet's cone
    friction instead of its pyramid. ``shape_overrides``:
    (obj_id, kind) pairs forcing an object's collision shape kind (see ``collision``). ``sleep_calm``: a body at rest
    by the test above sleeps (Bullet skips it) until a moving body touches it; see ``PhysicsProjector._simulate``.
    """

    # 1/120 s with 30 solver iterations settles a 4-box particle in half the time of 1/240 s with 60, with
    # rest poses within ~1 mm (median; 3.5 mm p90) of those: well inside the filter's 1 cm diffusion.
    timestep: float = 1.0 / 120.0
    solver_iterations: int = 30
    max_steps: int = 300
    # Measured on real meshes (benchmarks/real_physics.py): half these thresholds costs 20 % more steps for the
    # same resting poses against the unsimplified shapes.
    rest_linear: float = 0.02
    rest_angular: float = 0.2
    check_every: int = 4
    rest_checks: int = 2
    gravity: float = 9.81
    table_thickness: float = 0.05
    table_friction: float = 0.75
    off_table_z: float = -0.1
    max_speed: float = 10.0
    max_angular: float = 100.0
    max_distance: float = 2.0
    penetration_tolerance: float = 5e-4
    separation_iterations: int = 10
    # The solver stops iterating once its residual is below this: a third off the cost of a step on real meshes,
    # resting poses within 0.1 mm (median) of Bullet's default 1e-7 (benchmarks/real_physics.py). Bullet's
    # pyramid friction would save another quarter, but moved true resting scenes twice as far from those with
    # the unsimplified shapes (benchmarks/true_scene_drift.py --reference: median 3.1 mm against 1.4).
    solver_residual: float = 1e-4
    cone_friction: bool = True
    rolling_friction: float = 0.002
    spinning_friction: float = 0.002
    linear_damping: float = 0.04
    angular_damping: float = 0.04
    shape_overrides: tuple[tuple[int, str], ...] = ()
    sleep_calm: bool = True

    def __post_init__(self):
        positive = ("timestep", "solver_iterations", "solver_residual", "max_steps", "rest_linear", "rest_angular", "check_every",
                    "rest_checks", "table_thickness", "max_speed", "max_angular", "max_distance",
                    "penetration_tolerance", "separation_iterations")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"PhysicsConfig.{name}", f"must be a positive finite number, got {value!r}")
        for obj_id, kind in self.shape_overrides:
            if kind not in KINDS:
                raise InputError("PhysicsConfig.shape_overrides",
                                 f"object {obj_id}: kind must be one of {', '.join(KINDS)}, not {kind!r}")
        for name in ("gravity", "table_friction", "rolling_friction", "spinning_friction", "linear_damping",
                     "angular_damping"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"PhysicsConfig.{name}", f"must be a finite number >= 0, got {value!r}")
        if not (math.isfinite(self.off_table_z) and self.off_table_z < 0):
            raise InputError("PhysicsConfig.off_table_z",
                             f"must be below the table top (< 0), got {self.off_table_z!r}")


@dataclass(frozen=True)
class _BodyFrame:
    """Where Bullet's body sits in the object: its origin must be the centre of mass and its axes the principal
    axes, because Bullet takes the body frame as the inertial frame. ``T_obj_body`` (4, 4); ``inertia`` (3,)
    principal moments, kg m^2; ``support`` (N, 3) the shape's support points in the body frame."""

    T_obj_body: np.ndarray
    inertia: np.ndarray
    support: np.ndarray


def _body_frame(mesh: trimesh.Trimesh, shape: CollisionShape, mass: float) -> _BodyFrame:
    """A box or cylinder collides, and so moves, as a uniform box or cylinder: its own frame (a Bullet primitive
    cannot be offset from its body without wrapping it in a compound). Anything else keeps the mass distribution
    of the mesh (of its hull when the mesh is not watertight, matching ``ObjectModel.mass``)."""
    if shape.kind == BOX:
        T_obj_body = shape.T_obj_shape.copy()
        e2 = (2.0 * shape.half_extents) ** 2
        inertia = mass / 12.0 * np.array([e2[1] + e2[2], e2[0] + e2[2], e2[0] + e2[1]])
    elif shape.kind == CYLINDER:
        T_obj_body = shape.T_obj_shape.copy()
        r2, h2 = shape.half_extents[0] ** 2, (2.0 * shape.half_extents[2]) ** 2
        inertia = mass * np.array([(3 * r2 + h2) / 12.0, (3 * r2 + h2) / 12.0, r2 / 2.0])
    else:
        src = mesh if mesh.is_watertight else mesh.convex_hull
        I = np.asarray(src.moment_inertia, dtype=np.float64) * (mass / abs(float(src.mass)))
        inertia, axes = np.linalg.eigh(I)
        if np.linalg.det(axes) < 0:
            axes[:, 2] *= -1.0
        T_obj_body = make_pose(axes, np.asarray(src.center_mass, dtype=np.float64))
    T_body_obj = invert_pose(T_obj_body)
    support = shape.support_points() @ T_body_obj[:3, :3].T + T_body_obj[:3, 3]
    return _BodyFrame(T_obj_body, np.maximum(inertia, 1e-12), support)


def collision_shapes(models: list[ObjectModel], config: PhysicsConfig = PhysicsConfig(),
                     cache_dir: str | os.PathLike | None = None) -> list[CollisionShape]:
    """Each model's collision shape, chosen by fit (``collision.collision_shape_for``) unless
    ``config.shape_overrides`` names a kind for its ``obj_id``."""
    overrides = dict(config.shape_overrides)
    return [collision_shape_for(m.mesh, kind=overrides.get(m.obj_id), cache_dir=cache_dir) for m in models]


class PhysicsProjector:
    """Projects hypotheses of ``models`` resting on ``table`` to physically plausible ones.

    Owns one pybullet DIRECT client (create one projector per process; construction is self-contained, so it
    can happen inside a spawned worker). ``shapes``: the models' collision shapes if already computed (e.g. in
    the parent process, to run V-HACD once); ``cache_dir``: V-HACD's disk cache (see ``collision``).
    """

    def __init__(
        self,
        models: list[ObjectModel],
        table: Table,
        config: PhysicsConfig = PhysicsConfig(),
        shapes: list[CollisionShape] | None = None,
        cache_dir: str | os.PathLike | None = None,
    ):
        if shapes is None:
            shapes = collision_shapes(models, config, cache_dir)
        if len(shapes) != len(models):
            raise InputError("shapes", f"{len(shapes)} collision shapes for {len(models)} models")
        if not (table.x_min < table.x_max and table.y_min < table.y_max):
            raise InputError("table", f"empty table rectangle {table}")
        masses = [m.mass for m in models]
        for model, mass in zip(models, masses):
            if not (math.isfinite(mass) and mass > 0):
                raise InputError(model.source or f"model {model.obj_id}", f"mass must be positive, got {mass}")
        self.config = config
        self._models = list(models)
        self._table = table
        self._shapes = list(shapes)
        self._masses = masses
        self._frames = [_body_frame(m.mesh, s, mass) for m, s, mass in zip(models, shapes, masses)]
        self._T_obj_body = np.stack([f.T_obj_body for f in self._frames]) if models else np.zeros((0, 4, 4))
        self._T_body_obj = invert_pose(self._T_obj_body)
        self._inertia = [f.inertia.tolist() for f in self._frames]
        # Where the bodies wait between particles: beside the table, 1 m apart plus their sizes, so that no two
        # parked bodies (nor a body and the table) are near enough to touch.
        radius = max([float(np.max(np.linalg.norm(f.support, axis=1))) for f in self._frames], default=0.0)
        spacing = 2.0 * radius + 1.0
        self._parking = np.array([[table.x_max + spacing * (k + 1), table.y_max, spacing]
                                  for k in range(len(models))])
        self._tmpdir = tempfile.mkdtemp(prefix="workbench_physics_")
        self._client = pybullet.connect(pybullet.DIRECT)
        try:
            self._build_world()
        except BaseException:
            self.close()
            raise

    # ----------------------------------------------------------------------------------------------- world
    def _build_world(self) -> None:
        """Table and bodies, bodies parked far apart above the table until a particle places them."""
        cid, cfg, tb = self._client, self.config, self._table
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
        self._sink = 0.0
        # Bullet combines rolling (and spinning) friction as r_a * f_b + r_b * f_a (f: lateral friction), so the
        # table has none of its own: an object's contact with it gets rolling_friction * table_friction.
        pybullet.changeDynamics(self._table_body, -1, lateralFriction=cfg.table_friction, rollingFriction=0.0,
                                spinningFriction=0.0, physicsClientId=cid)
        self._shape_ids = []
        for k, (model, shape, frame) in enumerate(zip(self._models, self._shapes, self._frames)):
            shape_id = self._create_shape(k, shape, frame)
            if shape_id < 0:
                raise InputError(model.source or f"model {model.obj_id}", "Bullet rejected its collision shape")
            self._shape_ids.append(shape_id)
        self._bodies = []
        for k, (model, shape_id, mass) in enumerate(zip(self._models, self._shape_ids, self._masses)):
            body = pybullet.createMultiBody(mass, shape_id, basePosition=self._parking[k].tolist(),
                                            useMaximalCoordinates=True, physicsClientId=cid)
            # Margin 0: Bullet otherwise pads hulls by 1 mm, so hull objects would rest 1 mm above the table.
            # Sleeping off: Bullet would freeze a body that has moved slowly (< 0.8 m/s) for 2 s, resting or not.
            pybullet.changeDynamics(
                body, -1, mass=mass, localInertiaDiagonal=self._inertia[k], lateralFriction=model.friction,
                rollingFriction=cfg.rolling_friction, spinningFriction=cfg.spinning_friction,
                linearDamping=cfg.linear_damping, angularDamping=cfg.angular_damping, collisionMargin=0.0, activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING, physicsClientId=cid)
            self._bodies.append(body)

    def _create_shape(self, k: int, shape: CollisionShape, frame: _BodyFrame) -> int:
        cid = self._client
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

    @property
    def shapes(self) -> list[CollisionShape]:
        """The collision shape of each model, in model order (what each collides as, with its measured fit)."""
        return list(self._shapes)

    def close(self) -> None:
        if self._client is not None:
            pybullet.disconnect(physicsClientId=self._client)
            self._client = None
        shutil.rmtree(self._tmpdir, ignore_errors=True)

    def __enter__(self) -> "PhysicsProjector":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------ projection
    def project_batch(self, T_world_obj: np.ndarray, sink: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project B hypotheses one after the other. (B, K, 4, 4) -> resting poses (B, K, 4, 4), status (B,)
        int8, steps simulated (B,) int32. ``sink`` (B,) m: see ``project`` (default 0). Each result is the same
        as ``project`` of that hypothesis alone."""
        T = np.asarray(T_world_obj, dtype=np.float64)
        if T.ndim != 4:
            raise InputError("T_world_obj", f"expected shape (B, {len(self._bodies)}, 4, 4), got {T.shape}")
        sink = np.zeros(len(T)) if sink is None else np.asarray(sink, dtype=np.float64)
        out = np.empty_like(T)
        status = np.empty(len(T), dtype=np.int8)
        steps = np.empty(len(T), dtype=np.int32)
        for b in range(len(T)):
            out[b], status[b], steps[b] = self.project(T[b], float(sink[b]))
        return out, status, steps

    def project(self, T_world_obj: np.ndarray, sink: float = 0.0) -> tuple[np.ndarray, int, int]:
        """Simulate one hypothesis to rest. (K, 4, 4) -> (resting poses (K, 4, 4), status, steps simulated).

        ``sink`` (m): the surface the objects rest on lies this far below the table frame's z = 0 (the plane fitted
        to the table's depth); see ``Estimator`` for why it is estimated.

        Poses that are not finite or not rotations, or objects more than ``max_distance`` from the table, give
        STATUS_UNSTABLE with the input poses back; so does a simulation that blows up. Never raises for the
        values of the poses, only for a wrong shape.
        """
        T = np.asarray(T_world_obj, dtype=np.float64)
        K = len(self._bodies)
        if T.shape != (K, 4, 4):
            raise InputError("T_world_obj", f"expected shape ({K}, 4, 4), got {T.shape}")
        if K == 0:
            return T.copy(), STATUS_REST, 0
        if not np.all(np.isfinite(T)):
            return T.copy(), STATUS_UNSTABLE, 0
        T_wb = T @ self._T_obj_body
        R = T_wb[:, :3, :3]
        if np.max(np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3))) > 1e-3:
            return T.copy(), STATUS_UNSTABLE, 0
        quat = wxyz_to_xyzw(matrix_to_quat_wxyz(R))
        R = self._rotations(quat)  # exactly orthonormal, as Bullet will use them
        pos = T_wb[:, :3, 3].copy()
        if self._too_far(pos) or not math.isfinite(sink):
            return T.copy(), STATUS_UNSTABLE, 0
        self._set_sink(sink)
        self._separate(pos, R, quat)
        self._place(pos, quat)
        status, steps = self._simulate()
        poses = self._read_poses()
        if status == STATUS_UNSTABLE or not np.all(np.isfinite(poses)):
            # A blown-up world may hold non-finite state (bodies, broadphase): start the next particle afresh.
            self._build_world()
            return T.copy(), STATUS_UNSTABLE, steps
        return poses @ self._T_body_obj, status, steps

    def _set_sink(self, sink: float) -> None:
        """Put the table's top at z = -``sink`` (m); a static body moved between particles keeps no state."""
        if sink != self._sink:
            x, y, z = self._table_centre
            pybullet.resetBasePositionAndOrientation(self._table_body, [x, y, z - sink], [0.0, 0.0, 0.0, 1.0],
                                                     physicsClientId=self._client)
            self._sink = sink

    def _too_far(self, pos: np.ndarray) -> bool:
        """Is any body centre (K, 3) beyond ``max_distance`` around, above or below the table?"""
        tb, d = self._table, self.config.max_distance
        (x0, y0, z0), (x1, y1, z1) = pos.min(axis=0), pos.max(axis=0)
        return not (tb.x_min - d <= x0 and x1 <= tb.x_max + d and tb.y_min - d <= y0 and y1 <= tb.y_max + d
                    and -d <= z0 and z1 <= d)

    def _separate(self, pos: np.ndarray, R: np.ndarray, quat: np.ndarray) -> None:
        """Move the bodies (centres ``pos`` (K, 3), updated in place; rotations ``R`` (K, 3, 3) and ``quat``
        (K, 4) xyzw kept) out of the table and out of each other.

        Starting in penetration makes Bullet throw the objects (2 cm launches a box 16 cm). Each pass lifts every
        body whose lowest point is below the table top onto it, then moves each penetrating pair apart by its
        deepest penetration along the contact normal: sideways half each, upwards all on the upper body, so that
        no body is pushed into the table.
        """
        cfg, cid, bodies = self.config, self._client, self._bodies
        tol = cfg.penetration_tolerance
        for _ in range(cfg.separation_iterations):
            moved = False
            for k, frame in enumerate(self._frames):
                lowest = float(np.min(frame.support @ R[k, 2])) + pos[k, 2] + self._sink
                if lowest < -tol:
                    pos[k, 2] -= lowest
                    moved = True
            if len(bodies) < 2:
                break
            self._teleport(pos, quat)
            for a in range(len(bodies)):
                for b in range(a + 1, len(bodies)):
                    points = pybullet.getClosestPoints(bodies[a], bodies[b], 0.0, physicsClientId=cid)
                    if not points:
                        continue
                    deepest = min(points, key=lambda p: p[8])
                    if deepest[8] >= -tol:
                        continue
                    # contactNormalOnB points from b to a: move a along it relative to b.
                    shift = np.asarray(deepest[7]) * -deepest[8]
                    pos[a, :2] += shift[:2] / 2
                    pos[b, :2] -= shift[:2] / 2
                    if shift[2] > 0:
                        pos[a, 2] += shift[2]
                    else:
                        pos[b, 2] -= shift[2]
                    moved = True
                    self._teleport(pos, quat)
            if not moved:
                break

    def _place(self, pos: np.ndarray, quat: np.ndarray) -> None:
        """Put the bodies at rest at (K, 3) / (K, 4) xyzw with no state left from earlier particles: one step
        parked far apart at these orientations first (see the module doc). Bodies the previous particle put to sleep
        are woken (with Bullet's own sleeping off again)."""
        cid = self._client
        for body in self._bodies:
            pybullet.changeDynamics(body, -1, activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING,
                                    physicsClientId=cid)
        self._teleport(self._parking, quat)
        pybullet.stepSimulation(physicsClientId=self._client)
        self._teleport(pos, quat)

    def _teleport(self, pos: np.ndarray, quat: np.ndarray) -> None:
        """Set the bodies' poses (K, 3) / (K, 4) xyzw, at rest."""
        cid, zero = self._client, [0.0, 0.0, 0.0]
        for k, body in enumerate(self._bodies):
            pybullet.resetBasePositionAndOrientation(body, pos[k].tolist(), quat[k].tolist(), physicsClientId=cid)
            pybullet.resetBaseVelocity(body, zero, zero, physicsClientId=cid)

    def _simulate(self) -> tuple[int, int]:
        """Step until at rest, off the table, blown up or at the step cap. -> (status, steps).

        A body calm at ``rest_checks`` checks in a row is at rest by the same test as the scene, and is put to sleep:
        Bullet then skips it (and its contact with the table) until a moving body touches it and wakes its island.
        Most particles move one object of several, so most bodies are calm long before the particle ends: 3.3 ->
        2.7 ms per particle on a 4-object real frame, 5.9 -> 4.9 on a 6-object one, resting poses as far from the
        unsimplified shapes' as when awake (benchmarks/real_physics.py)."""
        cfg, cid, bodies, tb = self.config, self._client, self._bodies, self._table
        step, get_vel = pybullet.stepSimulation, pybullet.getBaseVelocity
        get_pose = pybullet.getBasePositionAndOrientation
        sleep, asleep = pybullet.changeDynamics, pybullet.ACTIVATION_STATE_SLEEP
        lin2, ang2 = cfg.rest_linear ** 2, cfg.rest_angular ** 2
        max_v2, max_w2 = cfg.max_speed ** 2, cfg.max_angular ** 2
        lo_x, hi_x = tb.x_min - cfg.max_distance, tb.x_max + cfg.max_distance
        lo_y, hi_y = tb.y_min - cfg.max_distance, tb.y_max + cfg.max_distance
        steps, calm = 0, 0
        body_calm = [0] * len(bodies)
        while steps < cfg.max_steps:
            for _ in range(min(cfg.check_every, cfg.max_steps - steps)):
                step(physicsClientId=cid)
                steps += 1
            resting, off_table = True, False
            for i, body in enumerate(bodies):
                (vx, vy, vz), (wx, wy, wz) = get_vel(body, physicsClientId=cid)
                x, y, z = get_pose(body, physicsClientId=cid)[0]
                v2, w2 = vx * vx + vy * vy + vz * vz, wx * wx + wy * wy + wz * wz
                # "not <=" so that NaN counts as a blow-up.
                if (not (v2 <= max_v2 and w2 <= max_w2) or not (lo_x <= x <= hi_x and lo_y <= y <= hi_y)
                        or not (z <= cfg.max_distance)):
                    return STATUS_UNSTABLE, steps
                off_table |= z < cfg.off_table_z
                still = v2 <= lin2 and w2 <= ang2
                resting &= still
                body_calm[i] = body_calm[i] + 1 if still else 0
                # A sleeping body has exactly zero velocity; any other calm one is sent to sleep.
                if cfg.sleep_calm and body_calm[i] >= cfg.rest_checks and (v2 > 0.0 or w2 > 0.0):
                    sleep(body, -1, activationState=asleep, physicsClientId=cid)
            if off_table:
                return STATUS_OFF_TABLE, steps
            calm = calm + 1 if resting else 0
            if calm >= cfg.rest_checks:
                return STATUS_REST, steps
        return STATUS_STEP_CAP, steps

    def _read_poses(self) -> np.ndarray:
        """Current body poses in the table frame -> (K, 4, 4)."""
        cid = self._client
        states = [pybullet.getBasePositionAndOrientation(body, physicsClientId=cid) for body in self._bodies]
        return make_pose(self._rotations([q for _, q in states]), np.array([p for p, _ in states]))

    @staticmethod
    def _rotations(quat) -> np.ndarray:
        """xyzw quaternions (K, 4) -> rotations (K, 3, 3); pybullet's conversion, ~20x faster than numpy's for
        a handful of small arrays."""
        return np.array([pybullet.getMatrixFromQuaternion(q) for q in np.asarray(quat).tolist()]).reshape(-1, 3, 3)
