"""The physics projection in MuJoCo: ``MujocoProjector``, the same projection as ``PhysicsProjector`` (Bullet) behind
the same interface (``projector.Projector``), chosen with ``PhysicsConfig.backend = "mujoco"`` (``--physics
mujoco``).

A hypothesis is separated as for Bullet (lifted onto the table, penetrating pairs pushed apart along their deepest
contact), simulated from rest, and judged at rest, off the table, blown up or at the step cap by the same tests at
the same checks. Determinism needs no parking here: every particle starts from ``mj_resetData``, which clears all
state (warm starts included), so a result depends only on its own input.

``PhysicsConfig.sleep_calm`` is mirrored by MuJoCo's own sleeping (``mujoco_model``); ``solver_residual`` is
Bullet's alone: MuJoCo's Newton solver stops at its own tolerance.
"""

from __future__ import annotations

import math
import os

import numpy as np

from workbench.errors import InputError
from workbench.geometry import invert_pose, make_pose, matrix_to_quat_wxyz, quat_wxyz_to_matrix
from workbench.physics.bodies import body_frame, body_rotations, checked_masses
from workbench.physics.collision import CollisionShape
from workbench.physics.config import PhysicsConfig
from workbench.physics.mujoco_model import TABLE_GEOM, build_mjcf, damping, dof_lengths
from workbench.physics.projector import (
    STATUS_OFF_TABLE,
    STATUS_REST,
    STATUS_STEP_CAP,
    STATUS_UNSTABLE,
    Projector,
    collision_shapes,
    lift_onto_table,
    push_apart,
    too_far,
)
from workbench.problem.scene import ObjectModel, Table

INSTALL_HINT = "pip install 'workbench[mujoco]' (or: pip install mujoco==3.14.0)"


def require_mujoco():
    """The ``mujoco`` module, or InputError naming the missing package and how to install it."""
    try:
        import mujoco
    except ImportError as err:
        raise InputError("--physics", f"mujoco is not installed ({err}); install it: {INSTALL_HINT}") from None
    return mujoco


class MujocoProjector(Projector):
    """Projects hypotheses of ``models`` resting on ``table`` to physically plausible ones, with MuJoCo.

    Arguments as ``PhysicsProjector``'s. Owns one MuJoCo model and its data (create one projector per process).
    """

    def __init__(
        self,
        models: list[ObjectModel],
        table: Table,
        config: PhysicsConfig = PhysicsConfig(),
        shapes: list[CollisionShape] | None = None,
        cache_dir: str | os.PathLike | None = None,
    ):
        mujoco = require_mujoco()
        if shapes is None:
            shapes = collision_shapes(models, config, cache_dir)
        masses = checked_masses(models, table, shapes)
        self.config = config
        self._mj = mujoco
        self._table = table
        self._shapes = list(shapes)
        self.frames = [body_frame(m.mesh, s, mass) for m, s, mass in zip(models, shapes, masses)]
        self._T_obj_body = np.stack([f.T_obj_body for f in self.frames]) if models else np.zeros((0, 4, 4))
        self._T_body_obj = invert_pose(self._T_obj_body)
        try:
            self._model = mujoco.MjModel.from_xml_string(build_mjcf(models, table, config, shapes, self.frames,
                                                                    masses))
        except ValueError as err:
            raise InputError("collision shapes", f"MuJoCo rejected the model: {err}") from None
        self._model.dof_damping[:] = damping(self.frames, masses, config)
        self._model.dof_length[:] = dof_lengths(len(models), config)
        self._data = mujoco.MjData(self._model)
        self._table_geom = mujoco.mj_name2id(self._model, mujoco.mjtObj.mjOBJ_GEOM, TABLE_GEOM)
        self._table_z = float(self._model.geom_pos[self._table_geom, 2])
        # Each geom's body among the objects (-1: the table).
        self._geom_object = np.asarray(self._model.geom_bodyid, dtype=np.int64) - 1
        self._sink = 0.0
        self._collided = False  # whether the data's contacts are those of the bodies as placed

    @property
    def shapes(self) -> list[CollisionShape]:
        return list(self._shapes)

    @property
    def n_objects(self) -> int:
        return len(self.frames)

    def close(self) -> None:
        """Nothing to free: the model and data go with the projector."""

    def project(self, T_world_obj: np.ndarray, sink: float = 0.0) -> tuple[np.ndarray, int, int]:
        """Simulate one hypothesis to rest, as ``PhysicsProjector.project`` (the same statuses, the same inputs
        refused). (K, 4, 4) -> (resting poses (K, 4, 4), status, steps simulated)."""
        T = self._checked(T_world_obj)
        if len(T) == 0:
            return T.copy(), STATUS_REST, 0
        if not np.all(np.isfinite(T)):
            return T.copy(), STATUS_UNSTABLE, 0
        start = body_rotations(T, self._T_obj_body)
        if start is None:
            return T.copy(), STATUS_UNSTABLE, 0
        pos, R = start
        quat = matrix_to_quat_wxyz(R)
        R = quat_wxyz_to_matrix(quat)  # exactly the rotations MuJoCo will use
        if too_far(pos, self._table, self.config.max_distance) or not math.isfinite(sink):
            return T.copy(), STATUS_UNSTABLE, 0
        self._set_sink(sink)
        self._mj.mj_resetData(self._model, self._data)
        self._separate(pos, R, quat)
        status, steps = self._simulate()
        poses = self._object_poses()
        if status == STATUS_UNSTABLE or not np.all(np.isfinite(poses)):
            return T.copy(), STATUS_UNSTABLE, steps
        return poses, status, steps

    def _set_sink(self, sink: float) -> None:
        """Put the table's top at z = -``sink`` (m): a fixed geom's position is part of the model, not of the state."""
        self._model.geom_pos[self._table_geom, 2] = self._table_z - sink
        self._sink = sink

    def _place(self, pos: np.ndarray, quat: np.ndarray) -> None:
        """Bodies at (K, 3) m / (K, 4) wxyz, at rest."""
        qpos = self._data.qpos.reshape(-1, 7)
        qpos[:, :3], qpos[:, 3:] = pos, quat
        self._data.qvel[:] = 0.0
        self._collided = False

    def _separate(self, pos: np.ndarray, R: np.ndarray, quat: np.ndarray) -> None:
        """Move the bodies (centres ``pos`` (K, 3), updated in place; rotations ``R`` (K, 3, 3) and ``quat``
        (K, 4) wxyz kept) out of the table and out of each other, as ``PhysicsProjector._separate``, and place them
        there: each pass lifts the bodies onto the table, then pushes each penetrating pair apart by its deepest
        contact. MuJoCo's contacts of the placed bodies (margin 0: only penetrations) stand in for Bullet's
        closest points."""
        cfg, K = self.config, len(pos)
        tol = cfg.penetration_tolerance
        self._place(pos, quat)
        for _ in range(cfg.separation_iterations):
            moved = lift_onto_table(pos, R, self.frames, self._sink, tol)
            if K < 2:
                break
            self._place(pos, quat)
            for a in range(K):
                for b in range(a + 1, K):
                    shift = self._deepest(a, b)
                    if shift is None or np.linalg.norm(shift) <= tol:
                        continue
                    push_apart(pos, a, b, shift)
                    moved = True
                    self._place(pos, quat)
            if not moved:
                break
        self._place(pos, quat)

    def _deepest(self, a: int, b: int) -> np.ndarray | None:
        """How far (3,) m body ``a`` must move relative to body ``b`` to leave their deepest penetration, from the
        contacts of the bodies as placed; None when they do not touch."""
        mj, m, d = self._mj, self._model, self._data
        if not self._collided:  # once per placement, for all the pairs it leaves unmoved
            mj.mj_kinematics(m, d)
            mj.mj_collision(m, d)
            self._collided = True
        best, shift = 0.0, None
        for c in d.contact[:d.ncon]:
            pair = (self._geom_object[c.geom[0]], self._geom_object[c.geom[1]])
            if c.dist < best and pair in ((a, b), (b, a)):
                # The normal points from geom[0] to geom[1]: geom[0]'s body leaves along its opposite.
                away = -np.asarray(c.frame[:3]) * -c.dist
                best, shift = c.dist, away if pair[0] == a else -away
        return shift

    def _simulate(self) -> tuple[int, int]:
        """Step until at rest, off the table, blown up or at the step cap, checking every ``check_every`` steps as
        ``PhysicsProjector._simulate`` does. -> (status, steps)."""
        cfg, tb, mj, m, d = self.config, self._table, self._mj, self._model, self._data
        lin2, ang2 = cfg.rest_linear ** 2, cfg.rest_angular ** 2
        max_v2, max_w2 = cfg.max_speed ** 2, cfg.max_angular ** 2
        lo = np.array([tb.x_min - cfg.max_distance, tb.y_min - cfg.max_distance, -np.inf])
        hi = np.array([tb.x_max + cfg.max_distance, tb.y_max + cfg.max_distance, cfg.max_distance])
        qpos, qvel = d.qpos.reshape(-1, 7), d.qvel.reshape(-1, 6)
        steps, calm = 0, 0
        while steps < cfg.max_steps:
            n = min(cfg.check_every, cfg.max_steps - steps)
            mj.mj_step(m, d, nstep=n)
            steps += n
            v2 = np.einsum("ij,ij->i", qvel[:, :3], qvel[:, :3])
            w2 = np.einsum("ij,ij->i", qvel[:, 3:], qvel[:, 3:])
            xyz = qpos[:, :3]
            # "not <=" so that NaN counts as a blow-up.
            if not (np.all(v2 <= max_v2) and np.all(w2 <= max_w2) and np.all(lo <= xyz) and np.all(xyz <= hi)):
                return STATUS_UNSTABLE, steps
            if np.any(xyz[:, 2] < cfg.off_table_z):
                return STATUS_OFF_TABLE, steps
            calm = calm + 1 if np.all(v2 <= lin2) and np.all(w2 <= ang2) else 0
            if calm >= cfg.rest_checks:
                return STATUS_REST, steps
        return STATUS_STEP_CAP, steps

    def _object_poses(self) -> np.ndarray:
        """Current object poses in the table frame -> (K, 4, 4)."""
        qpos = self._data.qpos.reshape(-1, 7)
        return make_pose(quat_wxyz_to_matrix(qpos[:, 3:]), qpos[:, :3].copy()) @ self._T_body_obj
