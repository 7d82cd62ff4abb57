"""How well a rendered scene explains the observed depth, in log space.

Two models, selected by ``LikelihoodConfig.model``:
- ``"ssd"``: the paper's sum of squared per-pixel differences, as a Gaussian log-likelihood
  ``-sum((obs - pred)^2) / (2 sigma^2)``, residuals capped at ``max_residual``.
- ``"robust"`` (default): a per-pixel mixture of a Gaussian around the predicted depth and an outlier term (as in
  3DP3 / Bayes3D), so unmodelled clutter, sensor artefacts and holes cost a bounded amount. The outlier term is
  not symmetric: a reading in front of the predicted surface is something unmodelled occluding it (clutter, a
  hand), while a reading behind it means the sensor saw through the predicted surface, into space the hypothesis
  says is solid. That free-space violation is ``free_space`` times less likely than an occluding outlier.
  With ``clutter_floor`` set, a reading that no object is drawn on and that lies in front of the table (or off
  it) is unmodelled clutter: it scores at least ``clutter_floor``, so an object drawn over clutter gains only by
  what its own surface explains better than that (``background_loglik``).
Observed pixels with no reading (0) are ignored by both. The prediction at a pixel is the rendered object depth,
else the table-plane depth, else nothing (a pixel no hypothesis explains: an outlier for every particle alike).
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
    # robust only: the outlier density of a reading behind the predicted surface (seen through it) over that of a
    # reading in front of it (occluded). 1: the symmetric mixture.
    free_space: float = 1.0
    # robust only: the log-density (1/m) at least that a reading in front of the table (or off it) which no object
    # covers scores, as unmodelled clutter. Without it such a pixel is an outlier (about -3.4) and an object
    # laid over a tall distractor gains about 7 per pixel, which outweighs a thin object's own pixels (about 1.3
    # each). At 2 an object gains on a clutter pixel only where its surface lies within about 1.8 sigma of the
    # reading. None (the default): no floor. The floor also takes most of an object's gain for explaining its
    # own readings, so unplaced objects hide behind others; measured, it turned about as many objects wrong as
    # right: docs/benchmarks.md, "A clutter floor".
    clutter_floor: float | None = None

    def validate(self) -> None:
        from workbench.errors import InputError

        if self.model not in ("robust", "ssd"):
            raise InputError("likelihood.model", f"unknown likelihood model {self.model!r}; use 'robust' or 'ssd'")
        if not (self.sigma > 0 and np.isfinite(self.sigma)):
            raise InputError("likelihood.sigma", f"sigma must be a positive number of metres, got {self.sigma}")
        if not 0.0 < self.outlier_prob < 1.0:
            raise InputError("likelihood.outlier_prob", f"must lie in (0, 1), got {self.outlier_prob}")
        if not 0.0 < self.free_space <= 1.0:
            raise InputError("likelihood.free_space", f"must lie in (0, 1], got {self.free_space}")
        if self.clutter_floor is not None and not np.isfinite(self.clutter_floor):
            raise InputError("likelihood.clutter_floor", f"must be a finite log-density or None, got "
                                                         f"{self.clutter_floor}")


def predicted_depth(rendered: np.ndarray, background: np.ndarray) -> np.ndarray:
    """Objects in front of the table. ``rendered``: (B, H, W), 0 = no object; ``background``: (H, W), 0 = nothing.
    -> (B, H, W)."""
    return np.where(rendered > 0, rendered, background[None])


def _loglik(obs: np.ndarray, pred: np.ndarray, config: LikelihoodConfig) -> np.ndarray:
    """Log-likelihood of observed depths ``obs`` given predictions ``pred`` (same shape, 0 = no prediction), both
    with a reading. float32 in, float32 out."""
    r = obs - pred
    if config.model == "ssd":
        r = np.where(pred > 0, np.minimum(np.abs(r), config.max_residual), config.max_residual)
        return (-0.5 / config.sigma**2) * r * r
    scale = np.float32((1.0 - config.outlier_prob) / (config.sigma * np.sqrt(2.0 * np.pi)))
    inlier = scale * np.exp(np.float32(-0.5 / config.sigma**2) * r * r)
    outlier = np.float32(config.outlier_prob / config.depth_range)
    if config.free_space < 1.0:
        outlier = np.where((pred > 0) & (r > 0), outlier * np.float32(config.free_space), outlier)
    return np.log(np.where(pred > 0, inlier, 0.0) + outlier)


def background_loglik(obs: np.ndarray, background: np.ndarray, config: LikelihoodConfig) -> np.ndarray:
    """Log-likelihood of readings ``obs`` (> 0) where no object is drawn, given the table depth ``background``
    there (same shape, 0 = off the table): the table term, raised to ``clutter_floor`` where the reading lies in
    front of the table or off it (unmodelled clutter). float32 in, float32 out."""
    return _clutter_floor(_loglik(obs, background, config), obs, background, config)


def _clutter_floor(ll: np.ndarray, obs: np.ndarray, background: np.ndarray, config: LikelihoodConfig,
                   bare: np.ndarray | bool = True) -> np.ndarray:
    """``ll``, the table's term at pixels with readings ``obs`` and table depths ``background`` (same shape), raised
    to ``clutter_floor`` where the pixel is ``bare`` (no object drawn) and the reading is clutter."""
    if config.model == "ssd" or config.clutter_floor is None:
        return ll
    clutter = bare & ((background == 0) | (obs < background))
    return np.where(clutter, np.maximum(ll, np.float32(config.clutter_floor)), ll)


def pixel_loglik(observed: np.ndarray, background: np.ndarray, rendered: np.ndarray, config: LikelihoodConfig
                 ) -> np.ndarray:
    """Per-pixel log-likelihood. ``observed``, ``background``: (H, W); ``rendered``: (B, H, W), 0 = no object
    -> (B, H, W) float32, 0 where the observation has no reading."""
    observed = observed.astype(np.float32)
    obs = np.broadcast_to(observed[None], rendered.shape)
    rendered = rendered.astype(np.float32)
    table = background_loglik(observed, background.astype(np.float32), config)[None]
    ll = np.where(rendered > 0, _loglik(obs, rendered, config), table)
    return np.where(obs > 0, ll, 0.0).astype(np.float32)


def scene_loglik(
    observed: np.ndarray, background: np.ndarray, rendered: np.ndarray, config: LikelihoodConfig
) -> np.ndarray:
    """Log-likelihood of each rendered hypothesis: the sum of ``pixel_loglik`` over the image, computed only
    where objects were drawn. ``observed``, ``background``: (H, W); ``rendered``: (B, H, W), 0 = no object
    -> (B,) float64.

    Every hypothesis shares the empty-table term; only pixels covered by an object (a tenth of the region,
    typically) change it, so the cost follows the objects' area, not the image's."""
    obs = observed.astype(np.float32).ravel()
    bg = background.astype(np.float32).ravel()
    valid = obs > 0
    table_ll = np.where(valid, background_loglik(obs, bg, config), 0.0)  # (P,)
    flat = rendered.reshape(len(rendered), -1)
    b, p = np.nonzero((flat > 0) & valid[None])
    delta = _loglik(obs[p], flat[b, p], config) - table_ll[p]
    return float(table_ll.sum(dtype=np.float64)) + np.bincount(b, weights=delta, minlength=len(rendered))


def drawn_over_loglik(observed: np.ndarray, background: np.ndarray, base: np.ndarray, own: np.ndarray,
                      config: LikelihoodConfig) -> np.ndarray:
    """How much each of the depth images ``own`` (n, H, W) changes the log-likelihood of ``base`` (H, W) when drawn
    over it (the nearer surface kept per pixel; 0 = nothing drawn) -> (n,) float64: ``scene_loglik`` of each
    composite is ``scene_loglik`` of ``base`` plus this. Only the pixels where ``own`` is the nearer surface are
    computed, which for one object moved in a scene of several is a fraction of the covered pixels."""
    obs = observed.astype(np.float32).ravel()
    under = base.ravel()
    flat = own.reshape(len(own), -1)
    b, p = np.nonzero((flat > 0) & (obs > 0)[None] & ((under == 0)[None] | (flat < under[None])))
    table = background.astype(np.float32).ravel()[p]
    before = _clutter_floor(_loglik(obs[p], np.where(under[p] > 0, under[p], table), config),  # without ``own``
                            obs[p], table, config, under[p] == 0)
    delta = _loglik(obs[p], flat[b, p], config) - before
    return np.bincount(b, weights=delta, minlength=len(own))
