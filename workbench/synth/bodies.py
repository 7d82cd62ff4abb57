"""Given models as bodies of the generator's pybullet world, concave sides and all: a bowl that something leans on
upturned, a drill lying against a box, a mug beside a clamp. Bullet collides dynamic bodies only as convex pieces,
so each mesh collides as the V-HACD pieces of the physics package's decomposition (``workbench.physics.collision``,
its unsimplified "reference" kind: the mesh's convex hull where the mesh fills 80 % of it, else fine pieces that
stand at most 1-2 mm off YCB's bowl, mug, drill, clamps and scissors), cached on disk as the estimator's shapes are.

The body frame is the mesh's centre of mass along its principal axes (Bullet takes the body frame as the inertial
frame), and its stable poses are those about that centre of mass, so that a body put down in one stays in it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from workbench.geometry import make_pose
from workbench.physics.collision import REFERENCE, collision_shape_for
from workbench.synth.objects import MeshItem, model_mesh


@dataclass(frozen=True, eq=False)
class PieceBody:
    """A model's body. ``parts``: convex pieces' vertices (N_i, 3) in the object frame, metres; ``T_obj_body``
    (4, 4): the body frame (centre of mass, principal axes); ``inertia`` (3,): principal moments per kilogram,
    m^2; ``volume``: m^3 (of the hull where the mesh is not closed)."""

    parts: tuple[np.ndarray, ...]
    T_obj_body: np.ndarray
    inertia: np.ndarray
    volume: float

    @property
    def points(self) -> np.ndarray:
        """Every piece's vertices, object frame: the lowest point of the body in any pose is one of them. (N, 3)"""
        return np.concatenate(self.parts)

    def write_obj(self, path: Path) -> None:
        """The pieces in the body frame as a Wavefront OBJ, one ``o`` object per piece: pybullet builds a
        compound of convex hulls only from such a file."""
        lines, offset = [], 1
        T_body_obj = np.linalg.inv(self.T_obj_body)
        for i, part in enumerate(self.parts):
            hull = trimesh.convex.convex_hull(part @ T_body_obj[:3, :3].T + T_body_obj[:3, 3])
            lines.append(f"o part{i}")
            lines += [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in hull.vertices]
            lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in hull.faces]
            offset += len(hull.vertices)
        Path(path).write_text("\n".join(lines) + "\n")


def _solid(item: MeshItem) -> trimesh.Trimesh:
    """What the body's mass fills: the mesh, or its hull where the mesh is not closed."""
    mesh = model_mesh(item)
    return mesh if mesh.is_watertight else mesh.convex_hull


@functools.cache
def piece_body(item: MeshItem) -> PieceBody:
    """The model's body (computed once per model: V-HACD takes seconds, then comes from the disk cache)."""
    shape = collision_shape_for(model_mesh(item), kind=REFERENCE)
    solid = _solid(item)
    per_kg = np.asarray(solid.moment_inertia, dtype=np.float64) / abs(float(solid.mass))
    inertia, axes = np.linalg.eigh(per_kg)
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1.0
    T_obj_body = make_pose(axes, np.asarray(solid.center_mass, dtype=np.float64))
    return PieceBody(tuple(np.asarray(p, dtype=np.float64) for p in shape.parts), T_obj_body,
                     np.maximum(inertia, 1e-12), abs(float(solid.volume)))


@functools.cache
def piece_rotations(item: MeshItem, min_probability: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """The rotations in which the body rests on a plane (R_world_obj with a heading of 0, (S, 3, 3)) and how
    likely each is dropped at random (S,), summing to 1: the stable poses of its pieces' hull about the mesh's
    own centre of mass, the unlikely ones left out."""
    body = piece_body(item)
    hull = trimesh.convex.convex_hull(body.points)
    transforms, probability = trimesh.poses.compute_stable_poses(hull, center_mass=body.T_obj_body[:3, 3])
    keep = probability >= min_probability
    return np.asarray(transforms)[keep, :3, :3], probability[keep] / probability[keep].sum()
