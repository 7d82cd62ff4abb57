"""Statistics of a depth sensor's errors, measured against a reference depth (what a perfect sensor would read).

They are what ``synth.sensor.model``'s models are fitted to and checked against (``benchmarks/sensor_stats.py``): the
residual's spread and tails by depth and by angle of incidence, its spatial correlation length, the share of
missing readings at depth discontinuities, at grazing angles and elsewhere, and the flying pixels at
silhouettes. Pure functions on arrays: depth images are (H, W) metres, 0 = no reading, NaN in a reference =
unknown (neither object nor table); pixels are (u, v) = (column, row) with K mapping points to pixel centres.
"""

from __future__ import annotations

import numpy as np

from workbench.synth.sensor.model import discontinuities, incidence_angle  # noqa: F401 (re-exported)

MAD_TO_STD = 1.4826  # the MAD of a normal distribution times this is its standard deviation


def robust_std(x: np.ndarray) -> float:
    """1.4826 x the median absolute deviation from the median: the std of the bulk, blind to outliers.
    (N,) any unit -> same unit; NaN when empty."""
    x = np.asarray(x, dtype=np.float64).ravel()
    if x.size == 0:
        return float("nan")
    return float(MAD_TO_STD * np.median(np.abs(x - np.median(x))))


def tail_fraction(x: np.ndarray, k: float = 3.0) -> float:
    """Share of ``x`` (N,) farther than ``k`` robust stds from the median (a normal law gives 0.27 % at k = 3);
    NaN when empty."""
    x = np.asarray(x, dtype=np.float64).ravel()
    if x.size == 0:
        return float("nan")
    s = robust_std(x)
    return float(np.mean(np.abs(x - np.median(x)) > k * s)) if s > 0 else 0.0


def detrend(residual: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The residual (H, W) minus its least-squares affine fit a + b u + c v over ``mask`` (H, W) bool; 0 off the
    mask. Why: a ground-truth pose a few millimetres off, or a plane fitted to the table, leaves a smooth ramp in
    the residual that is no sensor error and would stretch its correlation length."""
    out = np.zeros(residual.shape, dtype=np.float64)
    if mask.sum() < 3:
        return out
    v, u = np.nonzero(mask)
    A = np.stack([np.ones(len(u)), u, v], axis=1).astype(np.float64)
    r = residual[mask].astype(np.float64)
    coef, *_ = np.linalg.lstsq(A, r, rcond=None)
    out[mask] = r - A @ coef
    return out


def autocorrelation(residual: np.ndarray, mask: np.ndarray, max_lag: int) -> np.ndarray:
    """Normalised autocorrelation of ``residual`` (H, W) over the pixels of ``mask`` (H, W) bool, at lags
    0..max_lag pixels along rows and columns (the two pooled) -> (max_lag + 1,), 1 at lag 0; NaN at lags with no
    pair of masked pixels. The residual's mean over the mask is removed first."""
    r = np.where(mask, residual - residual[mask].mean() if mask.any() else 0.0, 0.0).astype(np.float64)
    m = mask.astype(np.float64)
    var = float((r**2).sum() / max(m.sum(), 1.0))
    out = np.full(max_lag + 1, np.nan)
    if var <= 0:
        return out
    for lag in range(max_lag + 1):
        s = (r[:, lag:] * r[:, :r.shape[1] - lag]).sum() + (r[lag:, :] * r[:r.shape[0] - lag, :]).sum()
        n = (m[:, lag:] * m[:, :m.shape[1] - lag]).sum() + (m[lag:, :] * m[:m.shape[0] - lag, :]).sum()
        if n > 0:
            out[lag] = s / n / var
    return out


def correlation_length(acf: np.ndarray, level: float = float(np.exp(-1.0))) -> float:
    """Pixels: the first lag where ``acf`` (L,), 1 at lag 0, falls below ``level`` (1/e), interpolated linearly
    between lags; NaN when it never does within the lags given."""
    acf = np.asarray(acf, dtype=np.float64)
    below = np.nonzero(acf < level)[0]
    if not len(below):
        return float("nan")
    i = int(below[0])
    if i == 0:
        return 0.0
    a, b = acf[i - 1], acf[i]
    return float(i - 1 + (a - level) / (a - b))


def edge_band(reference: np.ndarray, jump: float, width: int) -> np.ndarray:
    """Pixels within ``width`` pixels of a jump larger than ``jump`` metres between two known neighbours of the
    reference depth (H, W) metres (NaN = unknown: no edge is seen there) -> (H, W) bool."""
    ref = np.asarray(reference, dtype=np.float64)
    return discontinuities(np.where(np.isfinite(ref), ref, np.nan), jump, width)


def hole_fractions(observed: np.ndarray, expected: np.ndarray, edge: np.ndarray, grazing: np.ndarray
                   ) -> dict[str, float]:
    """Share of pixels without a reading (``observed`` (H, W) metres == 0) among the pixels where a reading is
    expected (``expected`` (H, W) bool), in three disjoint groups: at ``edge`` (H, W) bool, at ``grazing`` (H, W)
    bool but not an edge, and elsewhere -> {"edge", "grazing", "elsewhere"}, NaN for an empty group, with the
    pixel counts under "n_edge", "n_grazing", "n_elsewhere"."""
    holes = np.asarray(observed) <= 0
    groups = {"edge": expected & edge, "grazing": expected & grazing & ~edge, "elsewhere": expected & ~edge & ~grazing}
    out: dict[str, float] = {}
    for name, g in groups.items():
        n = int(g.sum())
        out[name] = float(holes[g].mean()) if n else float("nan")
        out[f"n_{name}"] = n
    return out


def window_min_max(depth: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the nearest and farthest known depth (finite, > 0) within ``radius`` pixels (a square window):
    (H, W) metres -> two (H, W) arrays, NaN where the window holds none."""
    d = np.asarray(depth, dtype=np.float64)
    known = np.isfinite(d) & (d > 0)
    lo = np.where(known, d, np.inf)
    hi = np.where(known, d, -np.inf)
    h, w = d.shape
    plo, phi = np.pad(lo, radius, constant_values=np.inf), np.pad(hi, radius, constant_values=-np.inf)
    near, far = lo.copy(), hi.copy()
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            near = np.minimum(near, plo[radius + dy:radius + dy + h, radius + dx:radius + dx + w])
            far = np.maximum(far, phi[radius + dy:radius + dy + h, radius + dx:radius + dx + w])
    return np.where(np.isfinite(near), near, np.nan), np.where(np.isfinite(far), far, np.nan)


def explained(observed: np.ndarray, reference: np.ndarray, radius: int, margin: float) -> np.ndarray:
    """Readings within ``margin`` metres of some reference depth within ``radius`` pixels: (H, W) -> (H, W) bool.
    A sloped surface near a silhouette (a can's side) is then no flying pixel, whatever its depth."""
    obs = np.asarray(observed, dtype=np.float64)
    ref = np.pad(np.asarray(reference, dtype=np.float64), radius, constant_values=np.nan)
    h, w = obs.shape
    out = np.zeros(obs.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        for dy in range(2 * radius + 1):
            for dx in range(2 * radius + 1):
                out |= np.abs(obs - ref[dy:dy + h, dx:dx + w]) <= margin
    return out


def flying_fraction(observed: np.ndarray, reference: np.ndarray, edge: np.ndarray, radius: int, margin: float
                    ) -> tuple[float, int]:
    """Flying pixels: readings at ``edge`` (H, W) bool pixels that lie between the nearest and farthest reference
    depth within ``radius`` pixels and more than ``margin`` metres from every reference depth there (a reading
    that belongs to neither side of the silhouette). ``observed``, ``reference`` (H, W) metres. -> (their share of
    the edge pixels that have a reading, that count of pixels); NaN share when there is none. The window is wider
    than the edge band so that a silhouette a few pixels off (a ground-truth pose millimetres off) still finds both
    sides."""
    obs = np.asarray(observed, dtype=np.float64)
    near, far = window_min_max(reference, radius)
    with np.errstate(invalid="ignore"):
        pool = edge & (obs > 0) & np.isfinite(near) & (far - near > 2 * margin)
        flying = pool & (obs > near + margin) & (obs < far - margin) & ~explained(obs, reference, radius, margin)
    n = int(pool.sum())
    return (float(flying.sum() / n) if n else float("nan")), n


def box_sum(a: np.ndarray, radius: int) -> np.ndarray:
    """Sum of ``a`` (H, W) over each pixel's (2 radius + 1)^2 window (zeros beyond the image) -> (H, W), by a
    summed-area table."""
    c = np.pad(np.pad(a, radius).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    k, (h, w) = 2 * radius + 1, a.shape
    return c[k:k + h, k:k + w] - c[:h, k:k + w] - c[k:k + h, :w] + c[:h, :w]


def local_mean(x: np.ndarray, mask: np.ndarray, radius: int) -> np.ndarray:
    """Mean of ``x`` (H, W) over the ``mask`` (H, W) bool pixels of each (2 radius + 1)^2 window -> (H, W), NaN
    where the window holds none. Splits a residual into its slow part (this) and its fast part (the rest)."""
    m = np.asarray(mask, dtype=np.float64)
    total, count = box_sum(np.where(mask, x, 0.0).astype(np.float64), radius), box_sum(m, radius)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0.5, total / count, np.nan)


def binned_spread(residual: np.ndarray, key: np.ndarray, edges: np.ndarray, k: float = 3.0
                  ) -> list[dict[str, float]]:
    """Robust std and tail share (``tail_fraction`` at ``k``) of ``residual`` (N,) in bins of ``key`` (N,) with
    bin edges ``edges`` (B + 1,) -> B dicts {"lo", "hi", "n", "robust_std", "tail"} (NaN in an empty bin)."""
    residual, key = np.asarray(residual, dtype=np.float64), np.asarray(key, dtype=np.float64)
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (key >= lo) & (key < hi)
        out.append({"lo": float(lo), "hi": float(hi), "n": int(sel.sum()), "robust_std": robust_std(residual[sel]),
                    "tail": tail_fraction(residual[sel], k)})
    return out


def relative_difference(a: float, b: float) -> float:
    """|a - b| / |b|: how far a statistic ``a`` (generated) is from ``b`` (measured); NaN when b is 0 or NaN."""
    return float(abs(a - b) / abs(b)) if b and np.isfinite(b) and np.isfinite(a) else float("nan")
