"""BOP 2019's average recall of a pose (``bop_toolkit_lib``'s ``pose_error.mssd``/``mspd`` and ``eval_calc_scores``):
what papers and the BOP leaderboard report, so that our numbers compare with theirs.

- MSSD (m, ``metrics.mssd``): the maximum symmetry-aware surface distance, min over the model's symmetries S of
  max over its vertices x of |T_est x - T_gt S x|. AR_MSSD is the share of the thresholds ``MSSD_FRACTIONS`` x the
  object's diameter that the error is under.
- MSPD (px): the same with both points projected into the image, in pixels. AR_MSPD is the share of the
  thresholds ``MSPD_PIXELS`` x (image width / 640) that the error is under.
- AR = mean(AR_VSD, AR_MSSD, AR_MSPD) over a dataset's objects (``vsd`` gives AR_VSD); an object without an
  estimate recalls nothing.

The symmetries are the dataset's (models_info.json), a continuous one sampled as the toolkit does
(``continuous_steps``): a sample of a can turned 10 degrees about its axis moves its rim by 6 mm, more than the
smallest MSSD threshold of a small object.
"""

from __future__ import annotations

import numpy as np

MSSD_FRACTIONS = np.arange(1, 11) * 0.05  # of the object's diameter
MSPD_PIXELS = np.arange(1, 11) * 5.0  # at an image 640 px wide; scaled by width / 640
# bop_toolkit's max_sym_disc_step: between consecutive samples of a continuous symmetry, the point farthest from
# its axis moves at most this share of the object's diameter.
CONTINUOUS_STEP = 0.01


def continuous_steps() -> int:
    """Samples of one full turn about a continuous symmetry's axis (bop_toolkit: ceil(pi / CONTINUOUS_STEP))."""
    return int(np.ceil(np.pi / CONTINUOUS_STEP))


def _apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def _sym(symmetries: np.ndarray | None) -> np.ndarray:
    return np.eye(4)[None] if symmetries is None else np.asarray(symmetries, dtype=np.float64)


def project(K: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3), metres, z > 0 -> pixel coordinates (N, 2) with intrinsics ``K`` (3, 3)."""
    uvw = points @ np.asarray(K, dtype=np.float64).T
    return uvw[:, :2] / uvw[:, 2:3]


def mspd(T_gt: np.ndarray, T_est: np.ndarray, points: np.ndarray, K: np.ndarray,
         symmetries: np.ndarray | None = None) -> float:
    """MSPD (px) of poses (4, 4) in the camera frame, metres; ``points`` (N, 3) the model's vertices, object frame;
    ``K`` (3, 3) the intrinsics; ``symmetries`` (S, 4, 4) or None."""
    est = project(K, _apply(np.asarray(T_est, dtype=np.float64), points))
    return float(min(np.max(np.linalg.norm(est - project(K, _apply(T_gt @ S, points)), axis=-1))
                     for S in _sym(symmetries)))


def recall(error: float, thresholds: np.ndarray) -> float:
    """The share of ``thresholds`` that ``error`` is under (BOP: strictly); 0 for a missing (NaN or inf) error."""
    if not np.isfinite(error):
        return 0.0
    return float(np.mean(error < np.asarray(thresholds)))


def ar_mssd(error_m: float, diameter_m: float) -> float:
    """One object's share of AR_MSSD's thresholds."""
    return recall(error_m, MSSD_FRACTIONS * diameter_m)


def ar_mspd(error_px: float, width: int) -> float:
    """One object's share of AR_MSPD's thresholds, in an image ``width`` pixels wide."""
    return recall(error_px, MSPD_PIXELS * width / 640.0)
