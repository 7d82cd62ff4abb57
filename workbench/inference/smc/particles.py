"""Where the paper's particles come from: random initial scenes over the support region, and the diffusion's
Sigma. Gaussian diffusion and the other moves are in ``inference/``.

A particle is a scene hypothesis: (K, 4, 4) object poses in the table frame; a particle set is (N, K, 4, 4).
The state is either full 6-DoF or the paper's reduced (x, y, z, yaw) used for 3- and 4-object clutter, where
roll and pitch are never sampled (they stay as physics left them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.errors import InputError
from workbench.geometry import random_rotations, rot_z
from workbench.meshes.heavy import HEAVY_FACES, lowest_points
from workbench.problem.scene import ObjectModel, Table

STATES = ("6dof", "xyzyaw")


@dataclass(frozen=True)
class Sigma:
    """Standard deviations of the diffusion: metres for x, y, z (elevation), radians for the angles, which
    rotate the object about table-frame axes through its origin."""

    x: float = 0.01
    y: float = 0.01
    z: float = 0.01
    roll: float = np.radians(5.0)
    pitch: float = np.radians(5.0)
    yaw: float = np.radians(5.0)

    def as_array(self) -> np.ndarray:
        """-> (6,) in (x, y, z, roll, pitch, yaw) order."""
        return np.array([self.x, self.y, self.z, self.roll, self.pitch, self.yaw], dtype=np.float64)

    def validate(self) -> None:
        a = self.as_array()
        if not np.all(np.isfinite(a)) or np.any(a < 0):
            raise InputError("sigma", f"diffusion standard deviations must be finite and >= 0, got {a.tolist()}")


def initial_particles(
    rng: np.random.Generator, n: int, models: list[ObjectModel], table: Table, state: str
) -> np.ndarray:
    """n random scenes -> (n, K, 4, 4): each object uniformly over the table's object region, random heading
    (any orientation in 6-DoF), its lowest point between the table and half the largest object's size above it
    so that physics can also drop it onto another object."""
    lift = 0.5 * max(float(np.max(m.mesh.extents)) for m in models)
    out = np.zeros((n, len(models), 4, 4))
    out[..., 3, 3] = 1.0
    for k, model in enumerate(models):
        R = random_rotations(rng, n) if state == "6dof" else rot_z(rng.uniform(-np.pi, np.pi, n))
        if len(model.mesh.faces) > HEAVY_FACES:  # its hull alone would take seconds (a sphere's: all its vertices)
            lowest = lowest_points(R, model.mesh.vertices)
        else:  # the lowest point is a hull vertex: the hull's few hundred, not the mesh's thousands, are searched
            lowest = np.min(np.einsum("nij,vj->nvi", R, model.mesh.convex_hull.vertices)[..., 2], axis=1)  # (n,)
        out[:, k, :3, :3] = R
        out[:, k, 0, 3] = rng.uniform(table.region_min[0], table.region_max[0], n)
        out[:, k, 1, 3] = rng.uniform(table.region_min[1], table.region_max[1], n)
        out[:, k, 2, 3] = rng.uniform(0.0, lift, n) - lowest
    return out
