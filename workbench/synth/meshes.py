"""Watertight meshes that ``make-scenes`` builds itself: a can, a mug with a handle, and a cable (a tube).

All in metres. The can is a closed cylinder about z. The mug is a hollow cylinder (open at the top, with a
bottom) and a handle of rectangular section bent in a half ellipse, stitched into the outer wall by sharing the
wall's vertices, so that the mesh is one closed surface without boolean operations. Its collision shape for
pybullet (:func:`mug_collision_parts`) is a solid cylinder plus one box per handle segment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from workbench.geometry import make_pose

SECTIONS = 64  # around a cylinder: the polygon lies within 0.05 mm of a 4 cm radius


def can_mesh(radius: float, height: float, sections: int = SECTIONS) -> trimesh.Trimesh:
    """A closed cylinder about z, centred at the origin."""
    return trimesh.creation.cylinder(radius=radius, height=height, sections=sections)


@dataclass(frozen=True)
class MugShape:
    """A mug, metres. The body's axis is z, bottom at z = 0 before centring; the handle sticks out along +x."""

    radius: float = 0.04  # outer radius of the body
    height: float = 0.09
    wall: float = 0.005
    bottom: float = 0.006
    handle_reach: float = 0.024  # how far the handle's centre line reaches out from the wall
    handle_span: float = 0.05  # vertical distance between the handle's two ends (centre lines)
    handle_thickness: float = 0.008  # across the handle's bend; its width is ``handle_segments`` wall segments
    handle_segments: int = 3
    handle_steps: int = 16  # segments along the handle


def _handle_centre(s: MugShape, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre line of the handle and the unit normal of its bend (in the x-z plane) at ``phi`` in [0, pi]:
    phi = 0 at the top end (leaving the wall along +x), pi at the bottom end. -> ((n, 3), (n, 3))."""
    a, b, zc = s.handle_reach, s.handle_span / 2, s.height / 2
    c = np.stack([s.radius + a * np.sin(phi), np.zeros_like(phi), zc + b * np.cos(phi)], axis=-1)
    tangent = np.stack([a * np.cos(phi), np.zeros_like(phi), -b * np.sin(phi)], axis=-1)
    tangent /= np.linalg.norm(tangent, axis=-1, keepdims=True)
    normal = np.stack([-tangent[:, 2], np.zeros_like(phi), tangent[:, 0]], axis=-1)  # tangent x e_y
    return c, normal


def mug_mesh(s: MugShape = MugShape(), sections: int = SECTIONS) -> trimesh.Trimesh:
    """The mug as one watertight surface, centred on its bounding box (the model origin is the box centre)."""
    m, t = s.handle_segments, s.handle_thickness
    theta = 2 * np.pi * np.arange(sections) / sections - np.pi * m / sections  # segments 0..m-1 hold the handle
    zc, b = s.height / 2, s.handle_span / 2
    outer_z = [0.0, zc - b - t / 2, zc - b + t / 2, zc + b - t / 2, zc + b + t / 2, s.height]
    profile = [(s.radius, z) for z in outer_z] + [(s.radius - s.wall, s.height), (s.radius - s.wall, s.bottom)]
    verts = [np.zeros(3)]  # 0: centre of the outer bottom
    rings = []
    for r, z in profile:
        rings.append(len(verts) + np.arange(sections))
        verts.extend(np.stack([r * np.cos(theta), r * np.sin(theta), np.full(sections, z)], axis=-1))
    inner_centre = len(verts)
    verts.append(np.array([0.0, 0.0, s.bottom]))
    nxt = np.roll(np.arange(sections), -1)
    faces = [[0, rings[0][nxt[k]], rings[0][k]] for k in range(sections)]
    holes = {(1, k) for k in range(m)} | {(3, k) for k in range(m)}  # (ring below, segment): the handle's ends
    for i in range(len(rings) - 1):
        A, B = rings[i], rings[i + 1]
        for k in range(sections):
            if (i, k) not in holes:
                faces += [[A[k], A[nxt[k]], B[nxt[k]]], [A[k], B[nxt[k]], B[k]]]
    faces += [[rings[-1][k], rings[-1][nxt[k]], inner_centre] for k in range(sections)]

    # The handle: rings of 2 (m + 1) vertices, the first and last being the edges of the two holes.
    def hole_loop(lower: int) -> np.ndarray:
        return np.r_[rings[lower][: m + 1], rings[lower + 1][m::-1]]

    phi = np.linspace(0.0, np.pi, s.handle_steps + 1)[1:-1]
    c, normal = _handle_centre(s, phi)
    y = s.radius * np.sin(theta[: m + 1])  # the same widths as the wall's hole
    loops = [hole_loop(3)]
    for ci, ni in zip(c, normal):
        loops.append(len(verts) + np.arange(2 * (m + 1)))
        lower = [ci - t / 2 * ni + [0.0, yj, 0.0] for yj in y]
        upper = [ci + t / 2 * ni + [0.0, yj, 0.0] for yj in y[::-1]]
        verts.extend(lower + upper)
    loops.append(np.r_[rings[2][: m + 1], rings[1][m::-1]])  # at the bottom end the bend's inner side is on top
    L = 2 * (m + 1)
    for P, Q in zip(loops[:-1], loops[1:]):
        for j in range(L):
            faces += [[P[j], P[(j + 1) % L], Q[(j + 1) % L]], [P[j], Q[(j + 1) % L], Q[j]]]
    mesh = trimesh.Trimesh(np.array(verts), np.array(faces), process=True)
    trimesh.repair.fix_normals(mesh)  # one consistent outward winding (the handle's loop order decides its own)
    mesh.apply_translation(-_raw_bounds_centre(s))
    return mesh


def _raw_bounds_centre(s: MugShape) -> np.ndarray:
    """Centre of the mug's bounding box before centring (body bottom centre at the origin). -> (3,)"""
    x_max = s.radius + s.handle_reach + s.handle_thickness / 2
    return np.array([(x_max - s.radius) / 2, 0.0, s.height / 2])


def mug_collision_parts(s: MugShape = MugShape()) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Convex pieces of the mug for pybullet, in the centred mesh frame: ("cylinder", (radius, height, 0), T) for
    the (solid) body and ("box", half extents (3,), T) for each handle segment. T: (4, 4) piece -> mug."""
    shift = -_raw_bounds_centre(s)
    parts = [("cylinder", np.array([s.radius, s.height, 0.0]), make_pose(np.eye(3), shift + [0, 0, s.height / 2]))]
    width = 2 * s.radius * np.sin(np.pi * s.handle_segments / SECTIONS)
    phi = np.linspace(0.0, np.pi, s.handle_steps + 1)
    c, _ = _handle_centre(s, phi)
    for p, q in zip(c[:-1], c[1:]):
        x = (q - p) / np.linalg.norm(q - p)
        z = np.cross(x, [0.0, 1.0, 0.0])
        R = np.stack([x, [0.0, 1.0, 0.0], z], axis=-1)
        half = np.array([np.linalg.norm(q - p) / 2, width / 2, s.handle_thickness / 2])
        parts.append(("box", half, make_pose(R, shift + (p + q) / 2)))
    return parts


def tube_mesh(path: np.ndarray, radius: float, sides: int = 8) -> trimesh.Trimesh:
    """A closed tube of ``radius`` along a polyline ``path`` (P, 3) with P >= 2 (a cable), capped at both ends."""
    path = np.asarray(path, dtype=np.float64)
    d = np.gradient(path, axis=0)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0])
    side = np.cross(d, up)
    bad = np.linalg.norm(side, axis=-1) < 1e-6
    side[bad] = np.cross(d[bad], [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side, axis=-1, keepdims=True)
    other = np.cross(side, d)
    a = 2 * np.pi * np.arange(sides) / sides
    ring = np.cos(a)[None, :, None] * side[:, None] + np.sin(a)[None, :, None] * other[:, None]
    verts = (path[:, None] + radius * ring).reshape(-1, 3)
    P = len(path)
    idx = np.arange(P * sides).reshape(P, sides)
    nxt = np.roll(np.arange(sides), -1)
    faces = []
    for i in range(P - 1):
        for k in range(sides):
            faces += [[idx[i, k], idx[i, nxt[k]], idx[i + 1, nxt[k]]], [idx[i, k], idx[i + 1, nxt[k]], idx[i + 1, k]]]
    ends = len(verts) + np.arange(2)
    verts = np.vstack([verts, path[0], path[-1]])
    faces += [[ends[0], idx[0, nxt[k]], idx[0, k]] for k in range(sides)]
    faces += [[ends[1], idx[-1, k], idx[-1, nxt[k]]] for k in range(sides)]
    mesh = trimesh.Trimesh(verts, np.array(faces), process=True)
    trimesh.repair.fix_normals(mesh)
    return mesh
