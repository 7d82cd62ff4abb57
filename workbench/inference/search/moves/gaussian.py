"""Gaussian steps: the paper's joint diffusion of every object, and steps of one object at a time.

With K objects, a joint step that improves one object usually damages another, so most of the default search
moves one object and keeps the others. Both are symmetric (log-q correction 0). ``scales`` (K,) multiply Sigma per
object: coarse to fine, Sigma shrinks for an object whose particles agree (``object_scales``).
"""

from __future__ import annotations

import numpy as np

from workbench.geometry import euler_to_matrix
from workbench.inference.search.moves.proposal import Proposal, pick_objects
from workbench.inference.smc.particles import Sigma


def _step(rng: np.random.Generator, poses: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Gaussian step of poses (..., 4, 4) with standard deviations s (..., 6) (x, y, z m; roll, pitch, yaw rad
    about table axes through the object origin)."""
    noise = rng.normal(size=s.shape) * s
    out = poses.copy()
    out[..., :3, 3] += noise[..., :3]
    out[..., :3, :3] = euler_to_matrix(noise[..., 3:]) @ poses[..., :3, :3]
    return out


def _sigmas(sigma: Sigma, scales: np.ndarray, state: str) -> np.ndarray:
    """(K, 6) standard deviations per object."""
    s = sigma.as_array()
    if state == "xyzyaw":
        s = s * np.array([1, 1, 1, 0, 0, 1])
    return np.asarray(scales, dtype=np.float64)[:, None] * s[None]


def propose_joint(rng: np.random.Generator, parents: np.ndarray, sigma: Sigma, scales: np.ndarray,
                  state: str) -> Proposal:
    """Every object of every particle takes a Gaussian step. (B, K, 4, 4) -> Proposal."""
    s = np.broadcast_to(_sigmas(sigma, scales, state), parents.shape[:2] + (6,))
    return Proposal.symmetric(_step(rng, parents, s))


def propose_single(rng: np.random.Generator, parents: np.ndarray, sigma: Sigma, scales: np.ndarray, state: str,
                   weights: np.ndarray) -> Proposal:
    """One object per particle, drawn by ``weights`` (K,), takes a Gaussian step; the others stay.
    (B, K, 4, 4) -> Proposal."""
    out = parents.copy()
    ks = pick_objects(rng, len(parents), weights)
    idx = np.arange(len(parents))
    out[idx, ks] = _step(rng, parents[idx, ks], _sigmas(sigma, scales, state)[ks])
    return Proposal.symmetric(out)


def object_scales(projected: np.ndarray, weights: np.ndarray, sigma: Sigma, floor: float) -> np.ndarray:
    """Coarse to fine: per object, the weighted spread of its position over the particle set, relative to
    Sigma's x, clipped to [floor, 1]. ``projected`` (N, K, 4, 4), ``weights`` (N,) summing to 1 -> (K,)."""
    pos = projected[:, :, :3, 3]  # (N, K, 3)
    mean = np.einsum("n,nkd->kd", weights, pos)
    spread = np.sqrt(np.einsum("n,nk->k", weights, np.sum((pos - mean) ** 2, axis=-1)))  # (K,) metres
    return np.clip(spread / max(sigma.x, 1e-9), floor, 1.0)
