"""The uniform move (``kinds.Relocate``): objects to random places in the object region, dropped onto whatever is
below. It keeps every place reachable, whatever the other moves' data say."""

from __future__ import annotations

import numpy as np

from workbench.problem.scene import ObjectModel, Table


def random_relocations(
    rng: np.random.Generator, particles: np.ndarray, prob: float, models: list[ObjectModel], table: Table
) -> np.ndarray:
    """With probability ``prob`` per object, move it to a uniformly random place over the object region and drop
    it from just above the other objects, so that it lands on whatever is below: the table or another object
    (orientation kept). (N, K, 4, 4) -> (N, K, 4, 4).

    A small object that the filter settled in the wrong place (beside its neighbour instead of on top of it, or
    in another object's footprint) is otherwise only ever nudged by the diffusion; this gives it a way out."""
    out = particles.copy()
    move = rng.random(particles.shape[:2]) < prob
    if not move.any():
        return out
    reach = np.array([0.5 * float(np.linalg.norm(m.mesh.extents)) for m in models])  # (K,) centre to farthest corner
    for n, k in zip(*np.nonzero(move)):
        others = np.arange(len(models)) != k
        top = float(np.max(particles[n, others, 2, 3] + reach[others], initial=0.0))
        lowest = float(np.min(models[k].mesh.vertices @ particles[n, k, :3, :3].T, axis=0)[2])
        out[n, k, 0, 3] = rng.uniform(table.region_min[0], table.region_max[0])
        out[n, k, 1, 3] = rng.uniform(table.region_min[1], table.region_max[1])
        out[n, k, 2, 3] = top + rng.uniform(0.0, 0.02) - lowest
    return out
