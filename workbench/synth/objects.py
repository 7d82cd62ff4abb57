"""The objects scenes are built from (YCB-like boxes, a can, a mug), their model meshes, and the geometry of
placing them: how far an object reaches along a direction, how a box rests on a face, how far it tilts."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import trimesh

from workbench.geometry import rot_z
from workbench.synth.meshes import MugShape, can_mesh, mug_mesh

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


@dataclass(frozen=True, eq=False)  # compared and hashed by identity: a mesh is not a value
class MeshItem:
    """An object given by its mesh (metres, model frame), e.g. a BOP dataset's model (``make-scenes --models``)."""

    obj_id: int
    name: str
    mesh: trimesh.Trimesh
    kind: ClassVar[str] = "mesh"

    @property
    def extents(self) -> tuple[float, float, float]:
        return tuple(float(e) for e in self.mesh.extents)


Item = Box | Can | Mug | MeshItem

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
MUG = ROUND[1]
OBJECTS = BOXES + ROUND
OBJECT_BY_ID = {o.obj_id: o for o in OBJECTS}


def box_mesh(extents) -> trimesh.Trimesh:
    """A box centred at its origin, metres."""
    return trimesh.creation.box(extents=np.asarray(extents, dtype=np.float64))


@functools.cache
def model_mesh(item: Item) -> trimesh.Trimesh:
    """The object's model mesh (metres, model frame), built once and shared: not to be changed (see ``item_mesh``)."""
    if item.kind == "box":
        return box_mesh(item.extents)
    if item.kind == "can":
        return can_mesh(item.radius, item.height)
    if item.kind == "mesh":
        return item.mesh
    return mug_mesh(item.shape)


def item_mesh(item: Item) -> trimesh.Trimesh:
    """The object's model mesh (metres, model frame): a fresh copy, free to transform."""
    return model_mesh(item).copy()


@functools.cache
def stable_rotations(item: Item, min_probability: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """The rotations in which the object rests on a plane, each as R_world_obj with a heading of 0 (S, 3, 3), and
    how likely each is to end up in it dropped at random (S,) summing to 1: the stable poses of its convex hull
    (what rests on a flat table; trimesh, about the hull's centre of mass), the unlikely ones left out."""
    transforms, probability = trimesh.poses.compute_stable_poses(model_mesh(item).convex_hull)
    keep = probability >= min_probability
    return np.asarray(transforms)[keep, :3, :3], probability[keep] / probability[keep].sum()


def lying_rotation(item: Item, rng) -> np.ndarray:
    """A stable rotation of the object (``stable_rotations``, drawn by its likelihood) turned to a random heading
    about the vertical -> R_world_obj (3, 3)."""
    R, p = stable_rotations(item)
    return rot_z(rng.uniform(-np.pi, np.pi)) @ R[rng.choice(len(p), p=p)]


def reach(item: Item, R: np.ndarray, direction: np.ndarray) -> float:
    """How far the object with rotation R (3, 3) extends from its origin along a unit world direction (3,)."""
    if item.kind == "box":  # exact and symmetric; kept in closed form so that box scenes stay bit for bit
        return support_half_extent(R, item.extents, direction)
    return float(np.max(model_mesh(item).vertices @ (R.T @ direction)))


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
