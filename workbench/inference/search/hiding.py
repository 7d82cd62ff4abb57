"""Hiding places: where an object can rest out of the camera's sight, right behind another.

An object the depth hardly shows (hidden behind another) has no cluster of points of its own, so the data-driven
candidates never put it where it hides. The search then parks it where it does least harm, which is often on or
beside what another object should explain: on a generated two-box frame the hidden cube sat on the tall box, the
box lay on its side under it, and the two together outscored every one-object change (the box standing again
left the cube floating), though the box standing with the cube behind it scores 1,576 above them. ``polish.seat``
offers an object it has to move out of the way a place behind the object that pushed it out.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from workbench.geometry import invert_pose, rot_z
from workbench.inference.search.moves.resting import RestingPoses
from workbench.problem.problem import Problem

if TYPE_CHECKING:  # annotations only: the geometry module imports this one's neighbours
    from workbench.inference.search.geometry import SearchGeometry

GAP = 0.005  # m left between the hiding object and the one it hides behind; physics closes or keeps it
LIFT = 0.005  # m above its resting height that a hidden object starts; physics sets it down

Hide = Callable[[np.ndarray, int, int], np.ndarray]  # (scene (K, 4, 4), k, i) -> object k's pose (4, 4) behind i


def line_of_sight(problem: Problem, at: np.ndarray) -> np.ndarray:
    """The level direction (2,) from the camera to the point ``at`` (3,) m, table frame: the way that "behind"
    points there. Straight down (no level part) counts as the table's x axis."""
    d = at[:2] - invert_pose(problem.camera.T_cam_world)[:2, 3]
    n = float(np.linalg.norm(d))
    return d / n if n > 1e-9 else np.array([1.0, 0.0])


def _reach(R: np.ndarray, hull: np.ndarray, d: np.ndarray) -> float:
    """How far (m) an object of rotation R (3, 3) and convex-hull vertices ``hull`` (V, 3) reaches from its origin
    along the level direction ``d`` (2,)."""
    return float(np.max(hull @ R[:2].T @ d))


def hiding_place(problem: Problem, scene: np.ndarray, k: int, i: int, rest: RestingPoses, hull_k: np.ndarray,
                 hull_i: np.ndarray) -> np.ndarray:
    """Object k's pose (4, 4) resting on the table right behind object i of ``scene`` (K, 4, 4) as the camera
    sees it: on its lowest resting face (``rest``), its widest side across the line of sight, just clear of i
    (``GAP``) along it and ``LIFT`` above its resting height. ``hull_k``, ``hull_i``: convex-hull vertices (V, 3),
    object frames."""
    d = line_of_sight(problem, scene[i, :3, 3])
    face = int(np.argmin(rest.heights))
    R0 = rest.rotations[face]
    # The heading that makes it shallowest along the line of sight: the closer behind the one in front it ends, the
    # less of it shows over that one to a camera looking down.
    headings = [rot_z(np.arctan2(d[1], d[0]) + a) @ R0 for a in (0.0, np.pi / 2)]
    R = min(headings, key=lambda R: _reach(R, hull_k, d) + _reach(R, hull_k, -d))
    T = np.eye(4)
    T[:3, :3] = R
    distance = _reach(scene[i, :3, :3], hull_i, d) + GAP + _reach(R, hull_k, -d)
    T[:2, 3] = scene[i, :2, 3] + distance * d
    T[2, 3] = rest.heights[face] + LIFT
    return T


def hider(problem: Problem, geometry: SearchGeometry) -> Hide:
    """``hiding_place`` for the problem's objects, given their resting poses and convex hulls (``geometry``)."""
    rest, hulls = geometry.rest, geometry.hulls
    return lambda scene, k, i: hiding_place(problem, scene, k, i, rest[k], hulls[k], hulls[i])
