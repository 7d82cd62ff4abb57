"""How well a rendered scene explains the observed depth, in log space.

Two models, selected by ``LikelihoodConfig.model``:
- ``"ssd"``: the paper's sum of squared per-pixel differences, as a Gaussian log-likelihood
  ``-sum((obs - pred)^2) / (2 sigma^2)``, residuals capped at ``max_residual``.
- ``"robust"`` (default): a per-pixel mixture of a Gaussian around the predicted depth and an outlier term (as in
  3DP3 / Bayes3D), so unmodelled clutter, sensor artefacts and holes cost a bounded amount. The outlier term is
  not symmetric: a reading in front of the predicted surface is something unmodelled occluding it (clutter, a
  hand), while a reading behind it means the sensor saw through the predicted surface, into space the hypothesis
  says is solid. That free-space violation is ``free_space`` times less likely than an occluding outlier.
  With ``clutter_floor`` set, readings in front of the table (or off it) are cut into pieces of possible clutter
  (``clutter_segments``: joined where neighbours' depths agree). A piece the objects leave unclaimed (they claim
  fewer than ``CLAIM_SHARE`` of its readings, and are drawn over fewer than ``COVER_SHARE``) is unmodelled clutter:
  each of its readings scores at least ``clutter_floor``, and a reading an object claims there scores no more than
  it would without the object. A piece they claim, or lie mostly behind, has no floor. So an object gains on clutter
  only by explaining all of it, not by covering part of a distractor; an object hidden behind clutter costs nothing
  there; and an object drawn behind its own visible surface does not pass that surface off as clutter.
Observed pixels with no reading (0) are ignored by both. The prediction at a pixel is the rendered object depth,
else the table-plane depth, else nothing (a pixel no hypothesis explains: an outlier for every particle alike).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

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
    # robust only: the log-density (1/m) at least that a reading of an unclaimed clutter piece scores (module
    # docstring). Without it such a pixel is an outlier (about -3.4) and an object laid over part of a tall
    # distractor gains about 7 per pixel, which outweighs a thin object's own pixels (about 1.3 each). With it,
    # claiming part of a piece costs the floor on the rest of it. 2 is the Gaussian's value 1.8 sigma from its
    # centre. None: no floor. Measured in docs/journal/2026-11.md, "The floor weighed in halfway" (with the search's
    # schedule, EstimatorConfig.floor_from; from the start it lost dev frames, "Clutter pieces").
    clutter_floor: float | None = 2.0

    @property
    def floored(self) -> bool:
        """Whether the clutter floor is on (it applies to the robust model only)."""
        return self.model == "robust" and self.clutter_floor is not None

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


# The clutter floor's pieces: fewer readings than this are speckle (sensor noise at edges), not clutter.
CLUTTER_MIN_PIXELS = 20
# A piece is claimed by the objects, and loses its floor, once they claim this share of its readings: an object
# laid over part of unmodelled clutter must explain all of it, or leave it to the floor.
CLAIM_SHARE = 0.1
# Nor is a piece clutter once the objects are drawn over most of its readings (claiming them or lying behind them):
# readings that lie mostly within the objects' outline are taken as the objects' own surface, seen nearer than they
# are drawn, not as something unmodelled standing exactly in front of them. Without this, a box drawn several cm
# behind its own visible face claimed none of it and its readings scored the floor: on generated occluded frames the
# box 8 cm behind scored 10,000-20,000 log-units above the box 4 cm behind, and seen from 20-40 degrees up anywhere
# 3-14 cm behind scored alike, a plateau 4,000-8,000 below the truth. An object hidden behind clutter that shows
# mostly beside it (a majority of the piece's readings not over the object) keeps costing nothing there.
COVER_SHARE = 0.5


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


def clutter_segments(observed: np.ndarray, background: np.ndarray, config: LikelihoodConfig) -> np.ndarray:
    """The readings that may be unmodelled clutter, in pieces: readings more than ``sigma`` in front of the table
    (or off it), joined where 4-neighbours differ by less than ``2 sigma`` in depth; pieces of fewer than
    ``CLUTTER_MIN_PIXELS`` are speckle, not clutter. ``observed``, ``background``: (H, W) m, 0 = none
    -> (H, W) int32 labels 0..S-1, -1 = not clutter. Computed once per frame (``Problem.clutter``)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    obs = observed.astype(np.float32)
    h, w = obs.shape
    above = ((obs > 0) & ((background == 0) | (obs < background - np.float32(config.sigma)))).ravel()
    index = np.arange(h * w).reshape(h, w)
    firsts, seconds = [], []
    for a, b in ((index[:, :-1], index[:, 1:]), (index[:-1, :], index[1:, :])):  # right and lower neighbours
        a, b = a.ravel(), b.ravel()
        joined = above[a] & above[b] & (np.abs(obs.ravel()[a] - obs.ravel()[b]) < 2 * config.sigma)
        firsts.append(a[joined])
        seconds.append(b[joined])
    a, b = np.concatenate(firsts), np.concatenate(seconds)
    _, label = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(h * w, h * w)), directed=False)
    label = np.where(above, label, h * w)  # h * w: not clutter
    kept = np.bincount(label, minlength=h * w + 1)[: h * w] >= CLUTTER_MIN_PIXELS
    renumber = np.full(h * w + 1, -1, np.int32)
    renumber[np.nonzero(kept)[0]] = np.arange(kept.sum(), dtype=np.int32)
    return renumber[label].reshape(h, w)


def _raise(ll: np.ndarray, config: LikelihoodConfig) -> np.ndarray:
    """What the clutter floor adds to a pixel's term ``ll``: max(ll, floor) - ll."""
    return np.maximum(ll, np.float32(config.clutter_floor)) - ll


def _over_clutter(ll: np.ndarray, claims: np.ndarray, bare_ll: np.ndarray, config: LikelihoodConfig) -> np.ndarray:
    """What the clutter floor adds to a drawn pixel's term ``ll`` when its piece stays unclaimed (the piece is
    clutter), where the bare table scores ``bare_ll`` (the same shape, or broadcast to it): a reading the surface
    does not claim scores at least the floor (``_raise``); one it claims at most what it scores without the object
    (the floor, or the table's term where that is higher). An object that fits a few readings of a large piece of
    clutter gains nothing there (a marker laid flat on an unmodelled sheet gained 1.6 per reading, more than its
    own partly seen-through readings gave it), while a surface the sensor sees through still costs the free-space
    term."""
    floor = np.float32(config.clutter_floor)
    return np.where(claims, np.minimum(ll, np.maximum(bare_ll, floor)), np.maximum(ll, floor)) - ll


def _claims(obs: np.ndarray, pred: np.ndarray, config: LikelihoodConfig) -> np.ndarray:
    """Whether a surface drawn at ``pred`` claims the reading ``obs`` (same shapes): it is not behind it by more
    than 2 sigma, so the sensor sees it or sees through it. A surface further behind is occluded by something
    unmodelled: clutter explains that reading whether the object is there or not."""
    return obs >= pred - np.float32(2 * config.sigma)


def _drawn_terms(obs: np.ndarray, pred: np.ndarray, ll: np.ndarray, table_ll: np.ndarray, bare: np.ndarray,
                 config: LikelihoodConfig) -> tuple[np.ndarray, np.ndarray]:
    """At pixels with readings ``obs`` where a surface at ``pred`` is drawn and scores ``ll``, and where the bare
    table scores ``table_ll`` and would gain ``bare`` from the floor (same shapes): (whether the surface claims the
    reading, ``_claims``; what the floor then adds there if the reading's clutter piece stays unclaimed, minus
    ``bare``)."""
    claims = _claims(obs, pred, config)
    return claims, _over_clutter(ll, claims, table_ll, config) - bare


def _unclaimed(sizes: np.ndarray, claimed: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Which pieces stay clutter under each of n hypotheses -> (n, S) bool: of each piece's ``sizes`` (S,)
    readings, the hypothesis claims (``claimed`` (n, S)) fewer than ``CLAIM_SHARE`` and is drawn over (``covered``
    (n, S), claimed or not) fewer than ``COVER_SHARE``."""
    return (claimed < CLAIM_SHARE * sizes[None]) & (covered < COVER_SHARE * sizes[None])


def _unclaimed_gain(sizes: np.ndarray, bare: np.ndarray, claimed: np.ndarray, covered: np.ndarray,
                    change: np.ndarray) -> np.ndarray:
    """The clutter floor's gain for each of n hypotheses -> (n,) float64: over each piece that stays clutter
    (``_unclaimed`` of ``sizes`` (S,), ``claimed`` and ``covered`` (n, S)), the bare pixels' gain ``bare`` (S,) plus
    the ``change`` (n, S) its drawn pixels make."""
    return (_unclaimed(sizes, claimed, covered) * (bare[None] + change)).sum(axis=1)


def _per_piece(b: np.ndarray, piece: np.ndarray, values: np.ndarray, n: int, s: int) -> np.ndarray:
    """Sum ``values`` per (hypothesis ``b``, piece ``piece``) over pairs with a piece -> (n, s) float64."""
    on = piece >= 0
    return np.bincount(b[on] * s + piece[on], weights=values[on], minlength=n * s).reshape(n, s)


def _segments(observed: np.ndarray, background: np.ndarray, config: LikelihoodConfig,
              segments: np.ndarray | None) -> np.ndarray:
    return clutter_segments(observed, background, config) if segments is None else segments


def pixel_loglik(observed: np.ndarray, background: np.ndarray, rendered: np.ndarray, config: LikelihoodConfig,
                 segments: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel log-likelihood. ``observed``, ``background``: (H, W) (or any shape, when ``segments`` is given and
    the pixels hold every pixel of each clutter piece they touch); ``rendered``: (B, H, W), 0 = no object;
    ``segments``: the clutter pieces (``clutter_segments``; found here when the floor is on and none are given)
    -> (B, H, W) float32, 0 where the observation has no reading."""
    observed = observed.astype(np.float32)
    rendered = rendered.astype(np.float32)
    obs = np.broadcast_to(observed[None], rendered.shape)
    table = _loglik(observed, background.astype(np.float32), config)
    drawn = rendered > 0
    ll = np.where(drawn, _loglik(obs, rendered, config), table[None])
    if config.floored and rendered.size:
        segment = _segments(observed, background, config, segments).ravel()
        n, sizes = len(rendered), np.bincount(segment[segment >= 0])
        claims = drawn & _claims(obs, rendered, config) & (obs > 0)
        add = _over_clutter(ll, claims, table[None], config).reshape(n, -1)
        b, p = np.nonzero(np.broadcast_to(segment >= 0, (n, segment.size)))
        claimed = _per_piece(b, segment[p], claims.reshape(n, -1)[b, p], n, len(sizes))
        covered = _per_piece(b, segment[p], (drawn & (obs > 0)).reshape(n, -1)[b, p], n, len(sizes))
        unclaimed = _unclaimed(sizes, claimed, covered)[b, segment[p]]
        ll = ll.reshape(n, -1)
        ll[b[unclaimed], p[unclaimed]] += add[b[unclaimed], p[unclaimed]]
        ll = ll.reshape(rendered.shape)
    return np.where(obs > 0, ll, 0.0).astype(np.float32)


def scene_loglik(
    observed: np.ndarray, background: np.ndarray, rendered: np.ndarray, config: LikelihoodConfig,
    segments: np.ndarray | None = None,
) -> np.ndarray:
    """Log-likelihood of each rendered hypothesis: the sum of ``pixel_loglik`` over the image, computed only
    where objects were drawn. ``observed``, ``background``: (H, W); ``rendered``: (B, H, W), 0 = no object;
    ``segments``: as ``pixel_loglik`` -> (B,) float64.

    Every hypothesis shares the empty-table term; only pixels covered by an object (a tenth of the region,
    typically) change it, so the cost follows the objects' area, not the image's."""
    plain, floor = ImageTerms.of(observed, background, config, segments).scene(rendered)
    return plain + floor


def drawn_over_loglik(observed: np.ndarray, background: np.ndarray, base: np.ndarray, own: np.ndarray,
                      config: LikelihoodConfig, segments: np.ndarray | None = None) -> np.ndarray:
    """How much each of the depth images ``own`` (n, H, W) changes the log-likelihood of ``base`` (H, W) when drawn
    over it (the nearer surface kept per pixel; 0 = nothing drawn) -> (n,) float64: ``scene_loglik`` of each
    composite is ``scene_loglik`` of ``base`` plus this. Only the pixels where ``own`` is the nearer surface are
    computed, which for one object moved in a scene of several is a fraction of the covered pixels (and, with the
    clutter floor, the pieces those pixels lie on)."""
    plain, floor = ImageTerms.of(observed, background, config, segments).drawn_over(base, own)
    return plain + floor


@dataclass(frozen=True)
class ImageTerms:
    """What every hypothesis scored against one observation shares, computed once for a batch of them rather
    than at every call (a tracked frame's settling scores a dozen small batches, an assembly hundreds of drawn-over
    candidates): per pixel (P,) the readings ``obs`` (float32 m, 0 = none), the table's depth ``table`` and the term
    each reading scores with nothing drawn (``table_ll``, 0 where there is no reading; ``table_sum`` its sum);
    with the clutter floor on, each pixel's clutter piece ``segment`` (-1: none), the pieces' ``sizes`` (S,), what
    the floor adds to each bare reading of a piece (``bare``) and per piece (``bare_sum`` (S,))."""

    config: LikelihoodConfig
    obs: np.ndarray
    table: np.ndarray
    table_ll: np.ndarray
    table_sum: float
    segment: np.ndarray | None = None
    sizes: np.ndarray | None = None
    bare: np.ndarray | None = None
    bare_sum: np.ndarray | None = None

    @classmethod
    def of(cls, observed: np.ndarray, background: np.ndarray, config: LikelihoodConfig,
           segments: np.ndarray | None = None) -> "ImageTerms":
        """``observed``, ``background``: (H, W) m (or any shape, when ``segments`` of that shape is given and the
        pixels hold every pixel of each clutter piece they touch); ``segments``: as ``pixel_loglik``."""
        obs = observed.astype(np.float32).ravel()
        table = background.astype(np.float32).ravel()
        valid = obs > 0
        table_ll = np.where(valid, _loglik(obs, table, config), 0.0)
        terms = cls(config, obs, table, table_ll, float(table_ll.sum(dtype=np.float64)))
        if not config.floored:
            return terms
        segment = _segments(observed, background, config, segments).ravel()
        sizes = np.bincount(segment[segment >= 0])
        bare = np.where(valid & (segment >= 0), _raise(table_ll, config), 0.0)
        bare_sum = _per_piece(np.zeros_like(segment), segment, bare, 1, len(sizes))[0]
        return replace(terms, segment=segment, sizes=sizes, bare=bare, bare_sum=bare_sum)

    def scene(self, rendered: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``scene_loglik`` of each of ``rendered`` (B, ...) in its two parts -> ((B,), (B,)) float64: the
        mixture's log-likelihood without the clutter floor, and what the floor adds to it (zeros when it is off).
        The search weighs the second part in gradually (``EstimatorConfig.floor_from``)."""
        obs, config = self.obs, self.config
        flat = rendered.reshape(len(rendered), -1)
        b, p = np.nonzero((flat > 0) & (obs > 0)[None])
        ll = _loglik(obs[p], flat[b, p], config)
        out = self.table_sum + np.bincount(b, weights=ll - self.table_ll[p], minlength=len(rendered))
        floor = np.zeros(len(rendered))
        if self.segment is not None:
            segment, sizes = self.segment, self.sizes
            claims, add = _drawn_terms(obs[p], flat[b, p], ll, self.table_ll[p], self.bare[p], config)
            n, s = len(rendered), len(sizes)
            covered = _per_piece(b, segment[p], np.ones(len(p)), n, s)  # p: the drawn pixels with a reading
            floor = _unclaimed_gain(sizes, self.bare_sum, _per_piece(b, segment[p], claims, n, s), covered,
                                    _per_piece(b, segment[p], add, n, s))
        return out, floor

    def drawn_over(self, base: np.ndarray, own: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``drawn_over_loglik`` of ``own`` (n, ...) over ``base`` in the two parts of ``scene`` -> ((n,), (n,))
        float64."""
        obs, config = self.obs, self.config
        under = base.ravel()
        flat = own.reshape(len(own), under.size)
        b, p = np.nonzero((flat > 0) & (obs > 0)[None] & ((under == 0)[None] | (flat < under[None])))
        before = _loglik(obs[p], np.where(under[p] > 0, under[p], self.table[p]), config)  # without ``own``
        ll = _loglik(obs[p], flat[b, p], config)
        out = np.bincount(b, weights=ll - before, minlength=len(own)).astype(np.float64)  # int64 when empty
        floor = np.zeros(len(own))
        if self.segment is not None:
            segment, sizes, bare, table_ll = self.segment, self.sizes, self.bare, self.table_ll
            n, s = len(own), len(sizes)
            q = np.nonzero((under > 0) & (obs > 0))[0]  # the base's drawn pixels, the only ones its terms touch
            base_claims, base_add = np.zeros(len(obs)), np.zeros(len(obs))
            base_claims[q], base_add[q] = _drawn_terms(obs[q], under[q], _loglik(obs[q], under[q], config),
                                                       table_ll[q], bare[q], config)
            zero = np.zeros(len(q), np.int64)
            claimed = _per_piece(zero, segment[q], base_claims[q], 1, s)
            covered = _per_piece(zero, segment[q], np.ones(len(q)), 1, s)
            change = _per_piece(zero, segment[q], base_add[q], 1, s)
            claims, add = _drawn_terms(obs[p], flat[b, p], ll, table_ll[p], bare[p], config)
            own_claimed = claimed + _per_piece(b, segment[p], claims - base_claims[p], n, s)
            own_covered = covered + _per_piece(b, segment[p], under[p] == 0, n, s)  # newly drawn over
            own_change = change + _per_piece(b, segment[p], add - base_add[p], n, s)
            floor = (_unclaimed_gain(sizes, self.bare_sum, own_claimed, own_covered, own_change)
                     - _unclaimed_gain(sizes, self.bare_sum, claimed, covered, change)[0])
        return out, floor
