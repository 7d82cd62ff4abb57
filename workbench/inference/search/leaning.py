"""Starts for an object leaning on another: its flat side laid along a slanted planar patch of a cluster.

Every other start puts an object on one of its resting faces, upright on the table or on a surface, at some
heading: a box leaning 60 degrees on a block is none of these, and ICP from an upright start does not tilt it that
far (it slides onto the block's top instead). What the sensor sees of a leaning box is a slanted flat patch: its
upper side. So each such patch (normals agreeing within PATCH_TURN, tilted TILT_MIN to TILT_MAX from the vertical,
at least PATCH_POINTS points and PATCH_WIDTH across) proposes the object with each resting face's upper side on
the patch, through its centre, in HEADINGS headings from the patch's principal axis; physics then lets it
fall against whatever holds it.

Those starts are tried by polish only (``library``: the best of each patch), while the estimate is stuck, and never
drawn into particles: a real desk shows many slanted patches that are no leaning object (ycbv-real-dev scene 2: 5-6
per frame), and in the library that every particle draws from, objects laid on them sent the search astray
(docs/journal/2026-11.md, "Leaning starts"). Tried on the estimate, such a start wins only where the whole scene, after
physics, scores better with it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from workbench.geometry import make_pose, principal_heading, rot_z, rotvec_to_matrix
from workbench.inference.search.datadriven import (
    Library,
    candidate_weights,
    fit_scores,
    fitted_clusters,
)
from workbench.inference.search.moves.resting import RestingPoses, height
from workbench.inference.search.scenepoints import (
    ModelSamples,
    point_normals,
)
from workbench.problem.problem import Problem

if TYPE_CHECKING:  # annotations only: the geometry module imports this one's neighbours
    from workbench.inference.search.geometry import SearchGeometry

TILT_MIN = np.radians(15.0)  # a patch less tilted is a top, which the level starts cover
TILT_MAX = np.radians(75.0)  # a patch more tilted is a wall: an upright side, which the upright starts cover
PATCH_TURN = np.radians(10.0)  # normals within this of a patch's normal belong to it
PATCH_OFF = 0.01  # m; points farther than this from the patch's plane do not
PATCH_POINTS = 40  # points that make a patch
PATCH_WIDTH = 0.015  # m; a patch narrower than this across is an edge or a rim
MAX_PATCHES = 2  # per cluster, the largest
HEADINGS = 4  # per face and patch, 90 degrees apart: the face's principal axis along the patch's, and across
SEEDS = 300  # normals tried as a patch's normal


def slanted_patches(cluster: np.ndarray, eye: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The cluster's (P, 3) (table frame, m; seen from ``eye`` (3,)) slanted planar patches, at most MAX_PATCHES,
    greedily: the normal most other slanted points' normals agree with first -> [(centre (3,), unit normal (3,)
    facing the sensor, points (Q, 3))]."""
    if len(cluster) < PATCH_POINTS:
        return []
    normals = point_normals(cluster, eye)
    tilt = np.arccos(np.clip(normals[:, 2], -1.0, 1.0))
    left = np.nonzero((tilt >= TILT_MIN) & (tilt <= TILT_MAX))[0]
    out = []
    cos_turn = np.cos(PATCH_TURN)
    while len(out) < MAX_PATCHES and len(left) >= PATCH_POINTS:
        N = normals[left]
        seeds = left[np.linspace(0, len(left) - 1, min(SEEDS, len(left))).astype(int)]
        agree = normals[seeds] @ N.T > cos_turn  # (S, L)
        n = normals[seeds[int(np.argmax(agree.sum(axis=1)))]]
        alike = left[N @ n > cos_turn]
        n = normals[alike].mean(axis=0)
        n /= np.linalg.norm(n)
        centre = np.median(cluster[alike], axis=0)
        members = alike[np.abs((cluster[alike] - centre) @ n) < PATCH_OFF]
        left = np.setdiff1d(left, alike)
        if len(members) < PATCH_POINTS:
            continue
        points = cluster[members]
        flat = (points - points.mean(axis=0)) @ _tilt(n)  # in the patch's plane (and out of it, ~0)
        spread = np.linalg.svd(flat[:, :2] - flat[:, :2].mean(axis=0), compute_uv=False)
        if np.sqrt(12.0 / len(points)) * spread[-1] < PATCH_WIDTH:  # a uniform strip's width is sqrt(12) sigma
            continue
        out.append((points.mean(axis=0), n, points))
    return out


def _tilt(n: np.ndarray) -> np.ndarray:
    """The rotation (3, 3) that turns the vertical onto the unit vector ``n`` (3,) about a horizontal axis."""
    axis = np.cross([0.0, 0.0, 1.0], n)
    s = float(np.linalg.norm(axis))
    if s < 1e-9:
        return np.eye(3)
    return rotvec_to_matrix(axis / s * np.arctan2(s, n[2]))


def leaning_starts(patches: list[tuple[np.ndarray, np.ndarray, np.ndarray]], rest: RestingPoses, hull: np.ndarray
                   ) -> list[list[np.ndarray]]:
    """Per slanted patch of a cluster (``slanted_patches``), poses (4, 4) of the object (convex-hull vertices
    ``hull`` (V, 3)) with each resting face's upper side on it, through the patch's centre, in HEADINGS headings:
    the patch's principal axis along the face's."""
    out = []
    for centre, n, points in patches:
        out.append([])
        R_tilt = _tilt(n)
        heading = principal_heading(((points - centre) @ R_tilt)[:, :2])
        for f, R in enumerate(rest.rotations):
            top = height(R, hull)
            own = principal_heading((hull @ R.T)[:, :2])
            for i in range(HEADINGS):
                Rz = rot_z(heading - own + i * 2 * np.pi / HEADINGS)
                # At rest on face f the origin is heights[f] above the table and the upper side ``top`` above it.
                t = centre + R_tilt @ np.array([0.0, 0.0, rest.heights[f] - top])
                out[-1].append(make_pose(R_tilt @ Rz @ R, t))
    return out


def library(problem: Problem, clusters: list[np.ndarray], geometry: SearchGeometry) -> Library:
    """Per object, its best leaning start (``leaning_starts``, scored by ``datadriven.fit_scores``, not fitted
    further) on each slanted patch of the ``clusters`` (list of (P_i, 3), largest first; those
    ``datadriven.fitted_clusters`` keeps), seen from the observed points' viewpoint -> Library.

    Not fitted: ICP slides a leaning box off its patch, onto whatever it leans on (the generated gelatin box on
    the wood block ended 2 cm and 74 degrees from a start 0.5 cm and 6 degrees from it)."""
    cloud, rest, samples, hulls = geometry.points, geometry.rest, geometry.samples, geometry.hulls
    K = len(rest)
    found: list[list[tuple[float, np.ndarray]]] = [[] for _ in range(K)]
    for cluster in fitted_clusters(clusters, K):
        patches = slanted_patches(cluster, cloud.viewpoint)
        for k in range(K):
            found[k] += _best_per_patch(problem, leaning_starts(patches, rest[k], hulls[k]), samples[k])
    poses = [np.stack([T for _, T in f]) if f else np.zeros((0, 4, 4)) for f in found]
    return Library(poses, [candidate_weights(np.array([score for score, _ in f])) for f in found])


def _best_per_patch(problem: Problem, starts: list[list[np.ndarray]], samples: ModelSamples
                    ) -> list[tuple[float, np.ndarray]]:
    """Of each patch's starts (``leaning_starts``: per patch, poses (4, 4)), the one that ``fit_scores`` best ->
    [(score, pose)], a patch at a time."""
    out = []
    for poses in filter(None, starts):
        scores = fit_scores(problem, np.stack(poses), samples)
        out.append((float(scores.max()), poses[int(np.argmax(scores))]))
    return out
