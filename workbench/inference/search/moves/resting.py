"""Stable resting poses of each object on a plane, and the moves between them.

A resting pose is an orientation (3, 3) of the object, at heading 0, in which it rests on the table, with the
height (m) of its origin above the plane. A box-like mesh (one that fills at least ``BOX_FILL`` of its oriented
bounding box) rests on one of its 6 faces; any other mesh on the faces ``trimesh.poses.compute_stable_poses``
finds for its convex hull, one per side of its oriented bounding box (which side faces down), with the
probabilities it estimates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from workbench.geometry import rot_z
from workbench.inference.search.moves.proposal import Proposal, pick_objects
from workbench.meshes.heavy import mesh_key

BOX_FILL = 0.85
# A side of a non-box mesh is proposed with at least this probability: a drop rarely lands a marker on its end,
# but a scene can hold one standing (YCB-Video's large marker does).
MIN_PROB = 0.05
MAX_HULL_VERTICES = 4000  # YCB-Video's hulls have 314-3,277 vertices (the banana the most)
REDUCED_HULL_VERTICES = 1000  # stable poses of a hull of 1,000 vertices take about 1.5 s


@dataclass(frozen=True)
class RestingPoses:
    """``rotations``: (F, 3, 3) object -> table rotations resting on face f at heading 0; ``heights``: (F,) z of
    the object origin above the plane when resting; ``probs``: (F,) how often the object comes to rest so;
    ``box``: whether the mesh is box-like (its faces are its bounding box's)."""

    rotations: np.ndarray
    heights: np.ndarray
    probs: np.ndarray
    box: bool = False


def reduced_hull(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh's convex hull; one with more than ``MAX_HULL_VERTICES`` vertices (a finely tessellated sphere)
    rebuilt from ``REDUCED_HULL_VERTICES`` of them (seeded), within about a millimetre of it: stable poses and the
    oriented bounding box cost time that grows faster than the hull's faces (minutes for a 1.3M-face sphere)."""
    hull = mesh.convex_hull
    if len(hull.vertices) <= MAX_HULL_VERTICES:
        return hull
    keep = np.random.default_rng(0).choice(len(hull.vertices), REDUCED_HULL_VERTICES, replace=False)
    return trimesh.convex.convex_hull(np.asarray(hull.vertices)[keep])


def _box_source(mesh: trimesh.Trimesh, hull: trimesh.Trimesh) -> trimesh.Trimesh:
    """What the oriented bounding box is taken of: the mesh itself unless its hull was reduced. The box of the
    mesh and of its hull are the same box, but not always with the same axes in the same order and sign (a box's
    faces would come out in another order, and a seeded run would draw other faces)."""
    return mesh if hull is mesh.convex_hull else hull


def _faces_of_box(mesh: trimesh.Trimesh, hull: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray] | None:
    """The 6 face-down rotations of the mesh's oriented bounding box (that of its ``hull``) and their face areas,
    or None if the mesh is not box-like."""
    obb = _box_source(mesh, hull).bounding_box_oriented
    solid = mesh if mesh.is_watertight else hull
    if abs(float(solid.volume)) < BOX_FILL * float(obb.volume):
        return None
    axes = np.asarray(obb.primitive.transform)[:3, :3]  # box axes in the object frame (columns)
    ext = np.asarray(obb.primitive.extents)
    rots, areas = [], []
    for i in range(3):
        for sign in (1.0, -1.0):
            down = sign * axes[:, i]  # object-frame direction that must point to -z
            # Build a rotation whose third row maps `down` to -z: rows are table axes in object coordinates.
            z_row = -down
            x_row = axes[:, (i + 1) % 3]
            y_row = np.cross(z_row, x_row)
            rots.append(np.stack([x_row, y_row, z_row]))
            j, k = [a for a in range(3) if a != i]
            areas.append(ext[j] * ext[k])
    return np.array(rots), np.array(areas)


def resting_poses(mesh: trimesh.Trimesh, upright_only: bool = False) -> RestingPoses:
    """The stable resting poses of ``mesh`` (metres, object frame). ``upright_only``: only the model's own
    orientation (for the x, y, z, yaw state, which never samples roll and pitch). Computed once per process and
    shape: a dataset's frames load the same models again, and a banana's stable poses take seconds."""
    key = (mesh_key(mesh), upright_only)
    if key not in _RESTING:
        _RESTING[key] = _resting_poses(mesh, upright_only)
    return _RESTING[key]


_RESTING: dict[tuple[str, bool], RestingPoses] = {}


def _resting_poses(mesh: trimesh.Trimesh, upright_only: bool) -> RestingPoses:
    hull = reduced_hull(mesh)
    box = None
    if upright_only:
        rots = np.eye(3)[None]
        probs = np.ones(1)
    else:
        box = _faces_of_box(mesh, hull)
        if box is not None:
            rots, areas = box
            probs = areas / areas.sum()  # a larger face is the likelier one to land on
        else:
            transforms, probs = trimesh.poses.compute_stable_poses(hull, n_samples=1)
            axes = np.asarray(_box_source(mesh, hull).bounding_box_oriented.primitive.transform)[:3, :3]
            rots, probs = one_per_side(np.asarray(transforms)[:, :3, :3], np.asarray(probs, dtype=np.float64), axes)
    heights = -np.min(np.einsum("fij,vj->fvi", rots, hull.vertices)[..., 2], axis=1)
    out = RestingPoses(np.array(rots, dtype=np.float64), np.array(heights), np.array(probs, dtype=np.float64),
                       box is not None)
    for a in (out.rotations, out.heights, out.probs):  # shared by every caller (the cache): read only
        a.setflags(write=False)
    return out


def one_per_side(rots: np.ndarray, probs: np.ndarray, axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stable poses (F, 3, 3) with probabilities (F,), grouped by the side of the oriented bounding box (axes
    (3, 3), columns, object frame) that faces down: per side, its most probable pose, with the side's summed
    probability raised to at least MIN_PROB. -> (S <= 6, 3, 3), (S,) summing to 1.

    compute_stable_poses lists a round object lying down once per facet of its hull (a marker: 8 of its most
    probable 8 poses), which crowded standing poses out; one pose per side keeps every way up in reach, and
    Gaussian and ICP moves turn the object about its axis."""
    along = -rots[:, 2, :] @ axes  # (F, 3): the down direction in box axes
    axis = np.argmax(np.abs(along), axis=1)
    side = 2 * axis + (along[np.arange(len(rots)), axis] < 0)
    keep, mass = [], []
    for s in np.unique(side):
        members = np.nonzero(side == s)[0]
        keep.append(members[np.argmax(probs[members])])
        mass.append(probs[members].sum())
    p = np.maximum(np.array(mass) / np.sum(mass), MIN_PROB)
    return rots[keep], p / p.sum()


def lowest_point(R: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """z of the lowest vertex, relative to the origin, for rotations (..., 3, 3) -> (...)."""
    return np.min(np.einsum("...j,vj->...v", R[..., 2, :], vertices), axis=-1)


def highest_point(R: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """z of the highest vertex, relative to the origin, for rotations (..., 3, 3) -> (...)."""
    return -lowest_point(-R, vertices)


def height(R: np.ndarray, hull: np.ndarray) -> float:
    """Height (m) of an object with rotation R (3, 3) and convex-hull vertices ``hull`` (V, 3): its vertical
    extent."""
    z = hull @ R[2]
    return float(z.max() - z.min())


def propose_face(rng: np.random.Generator, parents: np.ndarray, rest: list[RestingPoses],
                 hulls: list[np.ndarray], weights: np.ndarray) -> Proposal:
    """Put one object per particle (drawn by ``weights`` (K,)) on a resting face drawn by its probabilities,
    at a random heading, with its lowest point where it was (so a stacked object stays stacked).
    (B, K, 4, 4) -> Proposal. Faces are drawn by probability, so the correction is log p(old face) - log p(new
    face), the old face being the resting pose nearest the object's current orientation."""
    out = parents.copy()
    ks = pick_objects(rng, len(parents), weights)
    log_q = np.zeros(len(parents))
    for b, k in enumerate(ks):
        rp = rest[k]
        f = rng.choice(len(rp.probs), p=rp.probs)
        R_old = parents[b, k, :3, :3]
        base = parents[b, k, 2, 3] + lowest_point(R_old, hulls[k])
        R = rot_z(rng.uniform(-np.pi, np.pi)) @ rp.rotations[f]
        out[b, k, :3, :3] = R
        out[b, k, 2, 3] = max(base, 0.0) - lowest_point(R, hulls[k]) + 1e-3
        # Reverse move: back to the old face, whose probability is that of the resting pose it is nearest to.
        old = _nearest_face(R_old, rp)
        log_q[b] = np.log(rp.probs[old]) - np.log(rp.probs[f])
    return Proposal(out, log_q)


def _nearest_face(R: np.ndarray, rp: RestingPoses) -> int:
    """The resting pose whose "down" direction (object frame) is closest to that of R."""
    down = -R[2]  # object-frame direction pointing to -z
    downs = -rp.rotations[:, 2, :]
    return int(np.argmax(downs @ down))


def propose_turn(rng: np.random.Generator, parents: np.ndarray, weights: np.ndarray) -> Proposal:
    """Turn one object per particle by 90, 180 or 270 degrees about the vertical through its origin: the moves
    that take a box from a wrong but locally good heading to the right one. Symmetric."""
    out = parents.copy()
    ks = pick_objects(rng, len(parents), weights)
    quarter = rng.integers(1, 4, len(parents)) * (np.pi / 2)
    idx = np.arange(len(parents))
    out[idx, ks, :3, :3] = rot_z(quarter) @ parents[idx, ks, :3, :3]
    return Proposal.symmetric(out)
