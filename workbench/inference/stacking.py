"""Onto another object, and off it again: the moves between "beside" and "on top of".

A Gaussian step of a centimetre cannot take a small box from the table onto its neighbour (physics drops it back)
nor take it off; these moves can, and physics and the weights judge the result like any other hypothesis.
"""

from __future__ import annotations

import numpy as np

from workbench.inference.proposal import Proposal, pick_objects
from workbench.inference.resting import lowest_point


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
            top = parents[b, j, 2, 3] - lowest_point(-parents[b, j, :3, :3], hulls[j])  # highest point of j
            out[b, k, :2, 3] = parents[b, j, :2, 3] + rng.normal(scale=0.3 * reach[j], size=2)
            out[b, k, 2, 3] = top - low + 2e-3
    return Proposal.symmetric(out)
