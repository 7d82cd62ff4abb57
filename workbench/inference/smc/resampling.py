"""Tiny pure functions on log-weights (after the `particles` library's resampling module).

Weights never leave log space until they are normalised; ``-inf`` marks a particle that must never be drawn
(unstable or off-table physics).
"""

from __future__ import annotations

import numpy as np


def log_sum_exp(lw: np.ndarray) -> float:
    """log(sum(exp(lw))) without overflow. ``lw``: (N,)."""
    m = np.max(lw)
    if not np.isfinite(m):
        return float(m)
    return float(m + np.log(np.sum(np.exp(lw - m))))


def normalised_weights(lw: np.ndarray) -> np.ndarray:
    """(N,) log-weights -> (N,) weights summing to 1. All ``-inf`` gives uniform weights."""
    lw = np.asarray(lw, dtype=np.float64)
    if not np.any(np.isfinite(lw)):
        return np.full(lw.shape, 1.0 / lw.size)
    return np.exp(lw - log_sum_exp(lw))


def ess(lw: np.ndarray) -> float:
    """Effective sample size 1 / sum(W^2) of (N,) log-weights, in [1, N]."""
    w = normalised_weights(lw)
    return float(1.0 / np.sum(w * w))


def temper_to_ess(loglik: np.ndarray, target_fraction: float, max_beta: float = 1.0) -> float:
    """The exponent beta in [0, max_beta] for which the weights exp(beta * loglik) keep an effective sample size of
    ``target_fraction * N`` (or max_beta if even that keeps more).

    A depth likelihood sums thousands of pixels, so raw weights put all mass on one particle; tempering to a fixed
    ESS keeps a constant selection pressure whatever the image size or sensor noise (adaptive SMC tempering).
    """
    loglik = np.asarray(loglik, dtype=np.float64)
    finite = np.isfinite(loglik)
    if finite.sum() <= 1:
        return max_beta
    target = target_fraction * finite.sum()
    ll = loglik[finite] - loglik[finite].max()
    if ess(max_beta * ll) >= target:
        return max_beta
    lo, hi = 0.0, max_beta
    for _ in range(60):  # ESS falls monotonically with beta, so bisection converges
        mid = 0.5 * (lo + hi)
        if ess(mid * ll) >= target:
            lo = mid
        else:
            hi = mid
    return lo


def systematic_resample(lw: np.ndarray, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """Indices (n,) drawn by systematic resampling from (N,) log-weights: one uniform, n evenly spaced points."""
    w = normalised_weights(lw)
    n = w.size if n is None else n
    positions = (rng.random() + np.arange(n)) / n
    cumulative = np.cumsum(w)
    cumulative[-1] = 1.0  # guards against round-off leaving the last point past the end
    return np.searchsorted(cumulative, positions, side="right").clip(0, w.size - 1)
