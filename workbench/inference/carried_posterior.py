"""A tracked frame's posterior: the previous frame's modes, carried and weighed again on the new view.

A full posterior sweep (``posterior.sweep``: every object's half turns and headings, each settled) costs seconds;
a tracked frame has about one. The modes the previous frame left open are what this view may decide, so each is
scored again here, as given, with the other objects where the new estimate has them, and their probabilities
follow from the new log-likelihood gaps (``posterior.object_modes``). A mode that the new view rules out drops
below ``posterior.MIN_PROBABILITY`` and is gone from then on.
"""

from __future__ import annotations

import time

import numpy as np

from workbench.inference.posterior import ObjectPosterior, Posterior, object_modes, position_spread
from workbench.inference.settle import Score
from workbench.problem import Problem

LAST_ESTIMATE = "the last frame's estimate"


def rescored(problem: Problem, scene: np.ndarray, loglik: float, previous: Posterior, score: Score,
             projected: np.ndarray, weights: np.ndarray) -> tuple[Posterior, int]:
    """The posterior of the settled ``scene`` (K, 4, 4, table frame; ``loglik`` as given) from the ``previous``
    frame's (same table frame): its modes scored again with ``score`` (scenes as given -> log-likelihoods); the
    position spread from this frame's particles (``projected`` (N, K, 4, 4), ``weights`` (N,)); the previous open
    heading range kept (it is about the estimate's heading, which tracking keeps) -> (the posterior, scenes
    scored)."""
    t0 = time.perf_counter()
    given = [(o.obj, m) for o in previous.objects for m in o.modes]
    scenes = np.repeat(scene[None], len(given), axis=0)
    for i, (k, mode) in enumerate(given):
        scenes[i, k] = mode.T
    ll = score(scenes) if len(scenes) else np.zeros(0)
    objects = []
    for o in previous.objects:
        k = o.obj
        # The last estimate is a candidate too: when the new one left it by more than the tolerances, it is a mode.
        candidates = [(m.T, float(ll[i]), LAST_ESTIMATE if m.what == "the estimate" else m.what)
                      for i, (j, m) in enumerate(given) if j == k]
        objects.append(ObjectPosterior(
            obj=k,
            modes=object_modes(scene[k], loglik, candidates, problem.models[k].symmetries, previous.temperature),
            position_spread_m=position_spread(projected, weights, scene[k], k),
            yaw_range_deg=o.yaw_range_deg))
    return Posterior(objects, previous.temperature, time.perf_counter() - t0), len(scenes)
