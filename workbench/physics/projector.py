"""Physics projection (PI-PF): simulate a hypothesis until it is at rest; the resting poses are its projection.

A hypothesis is the poses of the K objects in the table frame. ``PhysicsProjector.project`` pushes the objects out
of the table and out of each other, lets them fall and settle under gravity in Bullet (pybullet), and returns where
they came to rest, with how the simulation ended (``STATUS_*``). It simulates in one ``world.World``, reused for
every particle without a particle's result depending on the ones before.

``Projector`` is the interface it shares with MuJoCo's projector (``mujoco_projector``), and ``too_far``,
``lift_onto_table`` and ``push_apart`` the checks and separation steps both take, so that both backends refuse the
same inputs and start from the same separated poses.
"""

from __future__ import annotations

import math
import os
from abc import ABC, abstractmethod

import numpy as np

from workbench.errors import InputError
from workbench.physics.bodies import BodyFrame
from workbench.physics.bullet import pybullet
from workbench.physics.collision import CollisionShape, collision_shape_for
from workbench.physics.config import PhysicsConfig
from workbench.physics.world import World
from workbench.problem.scene import ObjectModel, Table

STATUS_REST, STATUS_STEP_CAP, STATUS_UNSTABLE, STATUS_OFF_TABLE = 0, 1, 2, 3
# Set by the evaluator, not here: at rest, but an object's centre lies outside the region where objects are seen, or
# outside the image (``evaluation.admissible``).
STATUS_OUTSIDE = 4
# Set by the evaluator: scored as given, not simulated (``Evaluator.evaluate(..., project=False)``).
STATUS_AS_GIVEN = 5
STATUS_NAMES = {STATUS_REST: "rest", STATUS_STEP_CAP: "step cap", STATUS_UNSTABLE: "unstable",
                STATUS_OFF_TABLE: "off the table", STATUS_OUTSIDE: "outside the object region or the view",
                STATUS_AS_GIVEN: "as given, not simulated"}


def collision_shapes(models: list[ObjectModel], config: PhysicsConfig = PhysicsConfig(),
                     cache_dir: str | os.PathLike | None = None) -> list[CollisionShape]:
    """Each model's collision shape, chosen by fit (``collision.collision_shape_for``) unless
    ``config.shape_overrides`` names a kind for its ``obj_id``."""
    overrides = dict(config.shape_overrides)
    return [collision_shape_for(m.mesh, kind=overrides.get(m.obj_id), cache_dir=cache_dir) for m in models]


def too_far(pos: np.ndarray, table: Table, max_distance: float) -> bool:
    """Is any body centre (K, 3) m beyond ``max_distance`` (m) around, above or below the table?"""
    tb, d = table, max_distance
    (x0, y0, z0), (x1, y1, z1) = pos.min(axis=0), pos.max(axis=0)
    return not (tb.x_min - d <= x0 and x1 <= tb.x_max + d and tb.y_min - d <= y0 and y1 <= tb.y_max + d
                and -d <= z0 and z1 <= d)


def lift_onto_table(pos: np.ndarray, R: np.ndarray, frames: list[BodyFrame], sink: float, tolerance: float) -> bool:
    """Lift every body (centres ``pos`` (K, 3) m, updated in place; rotations ``R`` (K, 3, 3)) whose lowest support
    point lies more than ``tolerance`` (m) below the table top (at z = -``sink``) onto it. -> whether any moved."""
    moved = False
    for k, frame in enumerate(frames):
        lowest = float(np.min(frame.support @ R[k, 2])) + pos[k, 2] + sink
        if lowest < -tolerance:
            pos[k, 2] -= lowest
            moved = True
    return moved


def push_apart(pos: np.ndarray, a: int, b: int, shift: np.ndarray) -> None:
    """Move bodies ``a`` and ``b`` (centres ``pos`` (K, 3), in place) apart by ``shift`` (3,) m, the way ``a``
    must move relative to ``b``: sideways half each, upwards all on the upper body, so that no body is pushed into
    the table."""
    pos[a, :2] += shift[:2] / 2
    pos[b, :2] -= shift[:2] / 2
    if shift[2] > 0:
        pos[a, 2] += shift[2]
    else:
        pos[b, 2] -= shift[2]


class Projector(ABC):
    """What every physics backend offers the evaluators: ``project`` one hypothesis, ``project_batch`` many, the
    models' ``shapes``, ``close`` (also as a context manager). Made by ``physics.make_projector``."""

    @property
    @abstractmethod
    def shapes(self) -> list[CollisionShape]:
        """The collision shape of each model, in model order (what each collides as, with its measured fit)."""

    @property
    @abstractmethod
    def n_objects(self) -> int:
        """K, the objects of every hypothesis."""

    @abstractmethod
    def project(self, T_world_obj: np.ndarray, sink: float = 0.0) -> tuple[np.ndarray, int, int]:
        """Simulate one hypothesis (K, 4, 4) to rest -> (resting poses (K, 4, 4), status, steps simulated)."""

    @abstractmethod
    def close(self) -> None:
        """Free the simulator."""

    def __enter__(self) -> "Projector":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def project_batch(self, T_world_obj: np.ndarray, sink: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project B hypotheses one after the other. (B, K, 4, 4) -> resting poses (B, K, 4, 4), status (B,)
        int8, steps simulated (B,) int32. ``sink`` (B,) m: see ``project`` (default 0). Each result is the same
        as ``project`` of that hypothesis alone."""
        T = np.asarray(T_world_obj, dtype=np.float64)
        if T.ndim != 4:
            raise InputError("T_world_obj", f"expected shape (B, {self.n_objects}, 4, 4), got {T.shape}")
        sink = np.zeros(len(T)) if sink is None else np.asarray(sink, dtype=np.float64)
        out = np.empty_like(T)
        status = np.empty(len(T), dtype=np.int8)
        steps = np.empty(len(T), dtype=np.int32)
        for b in range(len(T)):
            out[b], status[b], steps[b] = self.project(T[b], float(sink[b]))
        return out, status, steps

    def _checked(self, T_world_obj: np.ndarray) -> np.ndarray:
        """One hypothesis as float64 (K, 4, 4), or InputError for a wrong shape."""
        T = np.asarray(T_world_obj, dtype=np.float64)
        if T.shape != (self.n_objects, 4, 4):
            raise InputError("T_world_obj", f"expected shape ({self.n_objects}, 4, 4), got {T.shape}")
        return T


class PhysicsProjector(Projector):
    """Projects hypotheses of ``models`` resting on ``table`` to physically plausible ones, with Bullet.

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
        self.config = config
        self._table = table
        self._world = World(models, table, config, shapes)

    @property
    def shapes(self) -> list[CollisionShape]:
        return list(self._world.shapes)

    @property
    def n_objects(self) -> int:
        return len(self._world.bodies)

    def close(self) -> None:
        self._world.close()

    def project(self, T_world_obj: np.ndarray, sink: float = 0.0) -> tuple[np.ndarray, int, int]:
        """Simulate one hypothesis to rest. (K, 4, 4) -> (resting poses (K, 4, 4), status, steps simulated).

        ``sink`` (m): the surface the objects rest on lies this far below the table frame's z = 0 (the plane fitted
        to the table's depth); see ``Estimator`` for why it is estimated.

        Poses that are not finite or not rotations, or objects more than ``max_distance`` from the table, give
        STATUS_UNSTABLE with the input poses back; so does a simulation that blows up. Never raises for the
        values of the poses, only for a wrong shape.
        """
        T = self._checked(T_world_obj)
        world = self._world
        if len(T) == 0:
            return T.copy(), STATUS_REST, 0
        if not np.all(np.isfinite(T)):
            return T.copy(), STATUS_UNSTABLE, 0
        start = world.body_poses(T)
        if start is None:
            return T.copy(), STATUS_UNSTABLE, 0
        pos, R, quat = start
        if too_far(pos, self._table, self.config.max_distance) or not math.isfinite(sink):
            return T.copy(), STATUS_UNSTABLE, 0
        world.set_sink(sink)
        self._separate(pos, R, quat)
        world.place(pos, quat)
        status, steps = self._simulate()
        poses = world.object_poses()
        if status == STATUS_UNSTABLE or not np.all(np.isfinite(poses)):
            # A blown-up world may hold non-finite state (bodies, broadphase): start the next particle afresh.
            world.build()
            return T.copy(), STATUS_UNSTABLE, steps
        return poses, status, steps

    def _separate(self, pos: np.ndarray, R: np.ndarray, quat: np.ndarray) -> None:
        """Move the bodies (centres ``pos`` (K, 3), updated in place; rotations ``R`` (K, 3, 3) and ``quat``
        (K, 4) xyzw kept) out of the table and out of each other.

        Starting in penetration makes Bullet throw the objects (2 cm launches a box 16 cm). Each pass lifts every
        body whose lowest point is below the table top onto it, then moves each penetrating pair apart by its
        deepest penetration along the contact normal (``push_apart``).
        """
        cfg, world = self.config, self._world
        cid, bodies = world.client, world.bodies
        tol = cfg.penetration_tolerance
        for _ in range(cfg.separation_iterations):
            moved = lift_onto_table(pos, R, world.frames, world.sink, tol)
            if len(bodies) < 2:
                break
            world.teleport(pos, quat)
            for a in range(len(bodies)):
                for b in range(a + 1, len(bodies)):
                    points = pybullet.getClosestPoints(bodies[a], bodies[b], 0.0, physicsClientId=cid)
                    if not points:
                        continue
                    deepest = min(points, key=lambda p: p[8])
                    if deepest[8] >= -tol:
                        continue
                    # contactNormalOnB points from b to a: move a along it relative to b.
                    push_apart(pos, a, b, np.asarray(deepest[7]) * -deepest[8])
                    moved = True
                    world.teleport(pos, quat)
            if not moved:
                break

    def _simulate(self) -> tuple[int, int]:
        """Step until at rest, off the table, blown up or at the step cap. -> (status, steps).

        A body calm at ``rest_checks`` checks in a row is at rest by the same test as the scene, and is put to sleep:
        Bullet then skips it (and its contact with the table) until a moving body touches it and wakes its island.
        Most particles move one object of several, so most bodies are calm long before the particle ends: 3.3 ->
        2.7 ms per particle on a 4-object real frame, 5.9 -> 4.9 on a 6-object one, resting poses as far from the
        unsimplified shapes' as when awake (benchmarks/real_physics.py)."""
        cfg, tb = self.config, self._table
        cid, bodies = self._world.client, self._world.bodies
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
