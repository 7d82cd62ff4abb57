"""Onto another object, and off it again: the moves between "beside" and "on top of".

A Gaussian step of a centimetre cannot take a small box from the table onto its neighbour (physics drops it back)
nor take it off; these moves can, and physics and the weights judge the result like any other hypothesis.
``bases_under`` finds the other half of a stack: where an object must lie to carry a top seen above the table.
"""

from __future__ import annotations

import numpy as np

from workbench.geometry import rot_z
from workbench.inference.search.datadriven import fit_scores
from workbench.inference.search.moves.proposal import Proposal, pick_objects
from workbench.inference.search.moves.resting import (
    RestingPoses,
    height,
    highest_point,
    lowest_point,
)
from workbench.inference.search.scenepoints import ModelSamples
from workbench.problem.problem import Problem


def propose_stack(rng: np.random.Generator, parents: np.ndarray, hulls: list[np.ndarray],
                  weights: np.ndarray) -> Proposal:
    """For one object k per particle (drawn by ``weights`` (K,)): if it rests on something (its lowest point is
    more than 1 cm above the table), put it back on the table beside where it was; else put it on top of another
    object j, near j's centre. ``hulls``: per object its convex-hull vertices (V, 3), object frame.
    (B, K, 4, 4) -> Proposal. Treated as symmetric: "onto j" and "off again" are each other's reverse, drawn
    with the same object weights; the landing offsets are drawn from the same scale both ways."""
    out = parents.copy()
    K = parents.shape[1]
    ks = pick_objects(rng, len(parents), weights)
    reach = np.array([np.max(np.linalg.norm(h[:, :2], axis=1)) for h in hulls])  # (K,) horizontal radius
    for b, k in enumerate(ks):
        R = parents[b, k, :3, :3]
        low = lowest_point(R, hulls[k])
        base = parents[b, k, 2, 3] + low
        if base > 0.01 or K == 1:
            angle = rng.uniform(-np.pi, np.pi)
            shift = (reach[k] + rng.uniform(0.0, 0.03)) * np.array([np.cos(angle), np.sin(angle)])
            out[b, k, :2, 3] += shift
            out[b, k, 2, 3] = -low + 1e-3
        else:
            j = rng.choice([i for i in range(K) if i != k])
            top = parents[b, j, 2, 3] + highest_point(parents[b, j, :3, :3], hulls[j])
            out[b, k, :2, 3] = parents[b, j, :2, 3] + rng.normal(scale=0.3 * reach[j], size=2)
            out[b, k, 2, 3] = top - low + 2e-3
    return Proposal.symmetric(out)


# A base under a seen top. YCB-Video frame 2:1: the pudding box lies on the wood block, which the box hides from
# above and the can and the banana hide from the sides. Fitted to its few visible pixels, the block's best
# candidate was 1.9 cm and 33 degrees off, and the search settled on the box on the table beside it and the block
# standing (3,500 log-units below the truth). The box's own candidate on top (0.9 cm, 4 degrees) is found from
# its top surface; a block lying on a face as tall as the box's bottom is high, under the box, is then fixed but
# for its place and heading, and a grid over those finds it. Its few visible pixels do not pick one place: a block
# 3.5 cm off explains more of them than one 1 cm off, for most tops a few millimetres apart, while physics and the
# likelihood prefer the right one by 450 log-units. So the grid's best *distinct* places are refined, and the best
# BASES of them returned, for the whole scene to decide.
BASE_MIN = 0.02  # m; a top whose lowest point is lower than this rests on the table, not on a base
BASE_SLACK = 0.03  # m; a base face may stand this much taller or lower than the top's lowest point
BASE_SPAN, BASE_STEP = 0.06, 0.02  # m; the coarse grid of base centres around the top's centre
BASE_HEADINGS = 12  # coarse headings, 30 degrees apart
COARSE_SAMPLES = 200  # model samples per pose in the coarse grid
FINE_STARTS = 3  # coarse poses refined, each at least APART from the others
FINE_STEP, FINE_TURN = 0.015, np.radians(10.0)  # the fine grid around each: one step either way
BASES = 2  # refined bases returned, each at least APART from the others
APART = 0.02  # m


def bases_under(problem: Problem, top: np.ndarray, top_hull: np.ndarray, rest: RestingPoses, hull: np.ndarray,
                samples: ModelSamples) -> list[tuple[np.ndarray, float]]:
    """Object j's best poses (4, 4) as the base under a top object at pose ``top`` (4, 4) (convex-hull vertices
    ``top_hull`` (V, 3), object frame), each with its ``datadriven.fit_scores`` score, best first; none if the top
    rests on the table or j has no resting face (``rest``; hull vertices ``hull`` (W, 3)) about as tall as the
    top's lowest point is high (BASE_SLACK). The base lies on the table, its centre on a grid around the top's
    centre, in BASE_HEADINGS headings; the best FINE_STARTS distinct ones are refined on a finer grid, and the
    best BASES distinct refined poses returned."""
    bottom = top[2, 3] + lowest_point(top[:3, :3], top_hull)
    heights = np.array([height(R, hull) for R in rest.rotations])
    faces = np.nonzero(np.abs(heights - bottom) <= BASE_SLACK)[0]
    if bottom < BASE_MIN or not len(faces):
        return []
    offsets = np.arange(-BASE_SPAN, BASE_SPAN + 1e-9, BASE_STEP)
    grid = np.stack(np.meshgrid(offsets, offsets, indexing="ij"), axis=-1).reshape(-1, 2)
    turns = 2 * np.pi * np.arange(BASE_HEADINGS) / BASE_HEADINGS
    coarse = np.concatenate([_on_table(rot_z(turns) @ rest.rotations[f], hull, top[:2, 3] + grid)
                             for f in faces])
    step = max(1, len(samples.points) // COARSE_SAMPLES)
    few = ModelSamples(samples.points[::step], samples.normals[::step])
    score = fit_scores(problem, coarse, few, per_pixel=False)
    fine_grid = np.stack(np.meshgrid(*[FINE_STEP * np.arange(-1, 2)] * 2, indexing="ij"), axis=-1).reshape(-1, 2)
    poses, scores = [], []
    for i in _distinct(coarse[:, :3, 3], score, FINE_STARTS):
        fine = _on_table(rot_z(FINE_TURN * np.arange(-1, 2)) @ coarse[i, :3, :3], hull, coarse[i, :2, 3] + fine_grid)
        fine_score = fit_scores(problem, fine, samples)
        poses.append(fine[int(np.argmax(fine_score))])
        scores.append(float(fine_score.max()))
    return [(poses[i], scores[i]) for i in _distinct(np.array(poses)[:, :3, 3], np.array(scores), BASES)]


def _distinct(centres: np.ndarray, score: np.ndarray, n: int) -> list[int]:
    """Indices of the ``n`` best of ``centres`` (S, 3) m by ``score`` (S,), best first, each at least APART from
    the better ones kept."""
    kept: list[int] = []
    for i in np.argsort(-score, kind="stable"):
        if all(np.linalg.norm(centres[i] - centres[j]) >= APART for j in kept):
            kept.append(int(i))
            if len(kept) == n:
                break
    return kept


def _on_table(rotations: np.ndarray, hull: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Poses (R * C, 4, 4) of every rotation (R, 3, 3) at every centre (C, 2) (x, y, m), resting on the table."""
    out = np.zeros((len(rotations), len(centres), 4, 4))
    out[..., :3, :3] = rotations[:, None]
    out[..., :2, 3] = centres[None]
    out[..., 2, 3] = -lowest_point(rotations, hull)[:, None]
    out[..., 3, 3] = 1.0
    return out.reshape(-1, 4, 4)
