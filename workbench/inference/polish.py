"""Polish: systematic one- and two-object changes of the estimate itself.

The particle moves change one object of a *random* particle at a time, so a change that the estimate needs (its
mustard bottle put on the candidate where the data shows it; two objects that took each other's places exchanged)
is tried on the estimate only by chance; nor can a Gaussian step turn an object that came to rest turned by 180
degrees about the vertical (a mustard bottle with its nozzle to the wrong side) and shifted to fit that way.
Every time the candidates are refitted, these variants of the estimate
are evaluated like any hypothesis (physics, then the likelihood). A variant that beats the estimate becomes the
estimate and replaces the worst particles, so the particle set searches on from it.
"""

from __future__ import annotations

import numpy as np

from workbench.geometry import rot_z, rotation_angle
from workbench.inference.datadriven import Library
from workbench.inference.refine import refit
from workbench.inference.scenepoints import ModelSamples

PER_OBJECT = 4  # the best candidates of each object tried in place of its pose in the estimate
SAME_M, SAME_RAD = 0.01, np.radians(10.0)  # a candidate this close to the estimate's pose is no change
LIFT = 0.005  # m; exchanged objects start this far above their old height, and physics sets them down


def variants(estimate: np.ndarray, library: Library, points: np.ndarray, samples: list[ModelSamples],
             reach: np.ndarray) -> np.ndarray:
    """The estimate (K, 4, 4) with one object put on one of its best ``PER_OBJECT`` library candidates, for every
    object and candidate that differs from its pose in the estimate; with one object turned by 90, 180 or 270
    degrees about the vertical through its centre and refitted by ICP to the observed points ``points`` (P, 3)
    near it (``refine.refit``; ``reach`` (K,) m); then with every pair of objects exchanging their places (x, y), each
    keeping its own orientation and height. -> (V, K, 4, 4), V <= K * (PER_OBJECT + 3) + K (K - 1) / 2."""
    K = len(estimate)
    out = []
    for k in range(K):
        turned = np.repeat(estimate[k][None], 3, axis=0)
        turned[:, :3, :3] = rot_z(np.pi / 2 * np.arange(1, 4)) @ estimate[k, :3, :3]
        for T in refit(points, samples[k], reach[k], turned):
            scene = estimate.copy()
            scene[k] = T
            out.append(scene)
    for k in range(K):
        if not library.has(k):
            continue
        best = np.argsort(-library.weights[k], kind="stable")[:PER_OBJECT]
        for T in library.poses[k][best]:
            if (np.linalg.norm(T[:3, 3] - estimate[k, :3, 3]) < SAME_M
                    and rotation_angle(T[:3, :3].T @ estimate[k, :3, :3]) < SAME_RAD):
                continue
            scene = estimate.copy()
            scene[k] = T
            out.append(scene)
    for i in range(K):
        for j in range(i + 1, K):
            scene = estimate.copy()
            scene[i, :2, 3], scene[j, :2, 3] = estimate[j, :2, 3], estimate[i, :2, 3]
            scene[[i, j], 2, 3] += LIFT
            out.append(scene)
    return np.array(out).reshape(-1, K, 4, 4)
