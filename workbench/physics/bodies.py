"""Where a simulated body sits in its object, for every physics backend: its origin at the centre of mass and its
axes the principal axes of inertia (``BodyFrame``), and the starting poses of the bodies from a hypothesis's object
poses. Bullet takes the body frame as the inertial frame; MuJoCo is given the same frame so that both simulate the
same mass distribution."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh

from workbench.errors import InputError
from workbench.geometry import invert_pose, make_pose
from workbench.physics.collision import BOX, CYLINDER, CollisionShape
from workbench.problem.scene import ObjectModel, Table


@dataclass(frozen=True)
class BodyFrame:
    """Where the body sits in the object: ``T_obj_body`` (4, 4), origin at the centre of mass, axes the principal
    axes; ``inertia`` (3,) principal moments, kg m^2; ``support`` (N, 3) the shape's support points in the body
    frame."""

    T_obj_body: np.ndarray
    inertia: np.ndarray
    support: np.ndarray


def body_frame(mesh: trimesh.Trimesh, shape: CollisionShape, mass: float) -> BodyFrame:
    """A box or cylinder collides, and so moves, as a uniform box or cylinder: its own frame (a Bullet primitive
    cannot be offset from its body without wrapping it in a compound). Anything else keeps the mass distribution
    of the mesh (of its hull when the mesh is not watertight, matching ``ObjectModel.mass``). ``mass`` kg."""
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
        tensor = np.asarray(src.moment_inertia, dtype=np.float64) * (mass / abs(float(src.mass)))
        inertia, axes = np.linalg.eigh(tensor)
        if np.linalg.det(axes) < 0:
            axes[:, 2] *= -1.0
        T_obj_body = make_pose(axes, np.asarray(src.center_mass, dtype=np.float64))
    T_body_obj = invert_pose(T_obj_body)
    support = shape.support_points() @ T_body_obj[:3, :3].T + T_body_obj[:3, 3]
    return BodyFrame(T_obj_body, np.maximum(inertia, 1e-12), support)


def checked_masses(models: list[ObjectModel], table: Table, shapes: list[CollisionShape]) -> list[float]:
    """The models' masses (kg), once the models, their collision shapes and the table make a world to simulate:
    InputError for a shape count that is not the model count, an empty table rectangle or a mass that is not
    positive."""
    if len(shapes) != len(models):
        raise InputError("shapes", f"{len(shapes)} collision shapes for {len(models)} models")
    if not (table.x_min < table.x_max and table.y_min < table.y_max):
        raise InputError("table", f"empty table rectangle {table}")
    masses = [m.mass for m in models]
    for model, mass in zip(models, masses):
        if not (math.isfinite(mass) and mass > 0):
            raise InputError(model.source or f"model {model.obj_id}", f"mass must be positive, got {mass}")
    return masses


def body_rotations(T_world_obj: np.ndarray, T_obj_body: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The bodies' poses for finite object poses (K, 4, 4) and body frames (K, 4, 4): (centres (K, 3), rotations
    (K, 3, 3)), or None when the object poses' rotations are not rotations (off by more than 1e-3)."""
    T_wb = T_world_obj @ T_obj_body
    R = T_wb[:, :3, :3]
    if np.max(np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3))) > 1e-3:
        return None
    return T_wb[:, :3, 3].copy(), R


def parking(frames: list[BodyFrame], x: float, y: float) -> np.ndarray:
    """Where K bodies wait between particles (K, 3): in a row from (``x``, ``y``) beside the table, 1 m apart plus
    their sizes, so that no two parked bodies (nor a body and the table) are near enough to touch."""
    radius = max([float(np.max(np.linalg.norm(f.support, axis=1))) for f in frames], default=0.0)
    spacing = 2.0 * radius + 1.0
    return np.array([[x + spacing * (k + 1), y, spacing] for k in range(len(frames))])
