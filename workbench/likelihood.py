"""How well a rendered scene explains the observed depth, in log space.

Two models, selected by ``LikelihoodConfig.model``:
- ``"ssd"``: the paper's sum of squared per-pixel differences, as a Gaussian log-likelihood
  ``-sum((obs - pred)^2) / (2 sigma^2)``, residuals capped at ``max_residual``.
- ``"robust"`` (default): a per-pixel mixture of a Gaussian around the predicted depth and a uniform outlier term
  (as in 3DP3 / Bayes3D), so unmodelled clutter, sensor artefacts and holes cost a bounded amount.
Observed pixels with no reading (0) are ignored by both. The prediction at a pixel is the rendered object depth,
else the table-plane depth, else nothing (a pixel no hypothesis explains: outlier for every particle alike).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LikelihoodConfig:
    model: str = "robust"  # "robust" | "ssd"
    sigma: float = 0.01  # m; sensor noise plus model mismatch
    outlier_prob: float = 0.1  # robust only: share of pixels the scene model cannot explain
    depth_range: float = 3.0  # m; support of the uniform outlier density
    max_residual: float = 0.05  # m; ssd only: caps a pixel's residual so one far pixel cannot dominate

    def validate(self) -> None:
        from workbench.errors import InputError

        if self.model not in ("robust", "ssd"):
            raise InputError("likelihood.model", f"unknown likelihood model {self.model!r}; use 'robust' or 'ssd'")
        if not (self.sigma > 0 and np.isfinite(self.sigma)):
            raise InputError("likelihood.sigma", f"sigma must be a positive number of metres, got {self.sigma}")
        if not 0.0 < self.outlier_prob < 1.0:
            raise InputError("likelihood.outlier_prob", f"must lie in (0, 1), got {self.outlier_prob}")


def predicted_depth(rendered: np.ndarray, background: np.ndarray) -> np.ndarray:
    """Objects in front of the table. ``rendered``: (B, H, W), 0 = no object; ``background``: (H, W), 0 = nothing.
    -> (B, H, W)."""
    return np.where(rendered > 0, rendered, background[None])


def pixel_loglik(observed: np.ndarray, predicted: np.ndarray, config: LikelihoodConfig) -> np.ndarray:
    """Per-pixel log-likelihood. ``observed``: (H, W); ``predicted``: (B, H, W) -> (B, H, W) float32, 0 where the
    observation has no reading."""
    obs = observed[None].astype(np.float32)
    valid = obs > 0
    r = obs - predicted
    if config.model == "ssd":
        r = np.minimum(np.abs(r), config.max_residual)
        r = np.where(predicted > 0, r, config.max_residual)
        ll = -0.5 * (r / config.sigma) ** 2
    else:
        inlier = (1.0 - config.outlier_prob) * np.exp(-0.5 * (r / config.sigma) ** 2) / (
            config.sigma * np.sqrt(2.0 * np.pi)
        )
        outlier = config.outlier_prob / config.depth_range
        ll = np.log(np.where(predicted > 0, inlier, 0.0) + outlier)
    return np.where(valid, ll, 0.0).astype(np.float32)


def scene_loglik(observed: np.ndarray, predicted: np.ndarray, config: LikelihoodConfig) -> np.ndarray:
    """Log-likelihood of each hypothesis. (H, W), (B, H, W) -> (B,) float64."""
    return pixel_loglik(observed, predicted, config).sum(axis=(1, 2), dtype=np.float64)
