"""The one container every proposal kind returns."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Proposal:
    """``hypotheses``: (B, K, 4, 4) proposed scenes in the table frame; ``log_q_ratio``: (B,) log q(X | X*) -
    log q(X* | X), the Metropolis-Hastings correction (0 for symmetric moves)."""

    hypotheses: np.ndarray
    log_q_ratio: np.ndarray

    @staticmethod
    def symmetric(hypotheses: np.ndarray) -> "Proposal":
        return Proposal(hypotheses, np.zeros(len(hypotheses)))


def pick_objects(rng: np.random.Generator, n: int, weights: np.ndarray) -> np.ndarray:
    """One object index per particle, drawn with probabilities proportional to ``weights`` (K,) -> (n,) int."""
    p = np.asarray(weights, dtype=np.float64)
    p = p / p.sum()
    return rng.choice(len(p), size=n, p=p)
