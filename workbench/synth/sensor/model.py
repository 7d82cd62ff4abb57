"""A Kinect-like depth sensor model applied to noise-free synthetic depth.

Axial noise follows Nguyen, Izadi & Lovell (2012), "Modeling Kinect Sensor Noise for Improved 3D Reconstruction
and Tracking": sigma(z) = 1.2 mm + 1.9 mm * (z - 0.4 m)^2 / m^2. Structured-light sensors also lose readings
where the depth jumps (the projector's pattern is shadowed or smeared there) and at scattered pixels, and they
report depth in millimetre steps, up to a maximum range (OpenNI drops Kinect v1 readings beyond about 6 m, where
a large desk seen at a grazing angle lets the view reach the far floor).

Three models, chosen by name (``SENSORS``, ``make-scenes --sensor``): ``ideal`` (the ray-cast depth as it is),
``kinect-like`` (the model above: white axial noise, 1 mm steps, holes at edges and at random) and ``xtion``, measured
on YCB-Video's Asus Xtion frames (``benchmarks/sensor_stats.py ../shared/datasets/ycbv-real-dev``, 2026-12-06): noise
growing with z^2 in two spatially correlated parts (a fast one a few pixels long and a slow, low-frequency
distortion tens of pixels long, as structured-light sensors show on flat surfaces), a per-frame bias, holes at edges
and at grazing angles, and flying pixels between the two sides of a silhouette. Lengths across the image are angles
(milliradians), turned into pixels with the focal length: the real frames are registered to a 1067 px colour camera,
generated ones use 525 px.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import Literal, get_args

import numpy as np

from workbench.geometry import backproject

SensorName = Literal["ideal", "kinect-like", "xtion"]
# New sets are made with the sensor measured on real frames: a generated benchmark predicts real performance only as
# far as its sensor is real. kinect-like stays for the sets made before (the benchmarks' older figures name it).
DEFAULT_SENSOR: SensorName = "xtion"
SENSOR_NAMES: tuple[str, ...] = get_args(SensorName)


@dataclass(frozen=True)
class SensorModel:
    """Parameters of :func:`apply_sensor`. Lengths in metres."""

    sigma_base: float = 0.0012  # axial std at z_ref
    sigma_quad: float = 0.0019  # growth per (z - z_ref)^2, in metres per m^2
    z_ref: float = 0.4
    edge_jump: float = 0.02  # a neighbour this much nearer or farther marks a discontinuity
    edge_width: int = 1  # pixels lost on each side of a discontinuity
    edge_drop: float = 0.8  # probability that a pixel at a discontinuity has no reading
    random_drop: float = 0.02  # fraction of all pixels without a reading
    quantum: float = 0.001  # depth resolution
    max_range: float = 6.0  # no reading farther than this
    # The extensions below are off by default, so that the plain model stays the Kinect-like one bit for bit.
    noise_corr_mrad: float = 0.0  # the axial noise's correlation length (autocorrelation 1/e); 0: white
    sigma_angle: float = 0.0  # Nguyen et al.'s angular term: + this x z^1.5 x theta^2 / (pi/2 - theta)^2, metres
    max_angle_deg: float = 85.0  # ... with theta at most this (the term diverges at grazing incidence)
    outlier_share: float = 0.0  # share of pixels whose noise is ``outlier_scale`` times larger (heavier tails)
    outlier_scale: float = 3.0
    slow_sigma: float = 0.0  # std of a slow distortion field at 1 m, metres ...
    slow_power: float = 2.0  # ... growing as (z / 1 m)^slow_power
    slow_corr_mrad: float = 0.0  # ... and its correlation length
    bias_sigma: float = 0.0  # std of one offset added to a whole frame
    disparity_quantum: float = 0.0  # 1/m: steps of 1/z (depth steps of this x z^2); 0: ``quantum`` steps of z
    edge_mrad: float = 0.0  # when > 0, the edge band's half width as an angle (replaces ``edge_width``)
    grazing_deg: float = 90.0  # beyond this angle between the surface normal and the ray ...
    grazing_drop: float = 0.0  # ... a pixel has no reading with this probability
    flying: float = 0.0  # probability that a pixel at a depth jump reads a depth between its two sides


def axial_sigma(z: np.ndarray, model: SensorModel = SensorModel()) -> np.ndarray:
    """Standard deviation of the depth noise at depth ``z``. (...) metres -> (...) metres."""
    z = np.asarray(z, dtype=np.float64)
    return model.sigma_base + model.sigma_quad * (z - model.z_ref) ** 2


def discontinuities(depth: np.ndarray, jump: float, width: int = 1) -> np.ndarray:
    """Pixels within ``width`` pixels of a depth jump larger than ``jump`` (or of a missing reading).

    ``depth``: (H, W) metres, 0 = none -> (H, W) bool.
    """
    d = np.asarray(depth, dtype=np.float64)
    edge = np.zeros(d.shape, dtype=bool)
    # A pixel next to "no reading" counts as an edge too: the sensor sees a jump to the background there.
    dx = np.abs(np.diff(d, axis=1)) > jump
    dy = np.abs(np.diff(d, axis=0)) > jump
    edge[:, 1:] |= dx
    edge[:, :-1] |= dx
    edge[1:, :] |= dy
    edge[:-1, :] |= dy
    for _ in range(max(width - 1, 0)):
        grown = edge.copy()
        grown[1:, :] |= edge[:-1, :]
        grown[:-1, :] |= edge[1:, :]
        grown[:, 1:] |= edge[:, :-1]
        grown[:, :-1] |= edge[:, 1:]
        edge = grown
    return edge


def incidence_angle(depth: np.ndarray, K: np.ndarray, jump: float = 0.02) -> np.ndarray:
    """Angle between the viewing ray and the surface normal, from central differences of the back-projected
    ``depth`` (H, W) metres, (3, 3) -> (H, W) radians in [0, pi/2]; NaN where a neighbour is missing (0 or NaN)
    or across a depth jump larger than ``jump`` metres (no surface to take a normal of there)."""
    d = np.asarray(depth, dtype=np.float64)
    angle = np.full(d.shape, np.nan)
    if d.shape[0] < 3 or d.shape[1] < 3:
        return angle
    p = backproject(np.nan_to_num(d), K)
    ok = np.isfinite(d) & (d > 0)
    n = np.cross(p[1:-1, 2:] - p[1:-1, :-2], p[2:, 1:-1] - p[:-2, 1:-1])
    ray = p[1:-1, 1:-1]
    cos = np.abs(np.einsum("hwk,hwk->hw", n, ray)) / np.maximum(
        np.linalg.norm(n, axis=-1) * np.linalg.norm(ray, axis=-1), 1e-300)
    with np.errstate(invalid="ignore"):
        good = (ok[1:-1, 1:-1] & ok[1:-1, 2:] & ok[1:-1, :-2] & ok[2:, 1:-1] & ok[:-2, 1:-1]
                & (np.abs(d[1:-1, 2:] - d[1:-1, :-2]) < jump) & (np.abs(d[2:, 1:-1] - d[:-2, 1:-1]) < jump))
    angle[1:-1, 1:-1] = np.where(good, np.arccos(np.clip(cos, 0.0, 1.0)), np.nan)
    return angle


def correlated_noise(shape: tuple[int, int], length_px: float, rng: np.random.Generator) -> np.ndarray:
    """Unit-std Gaussian noise (H, W) whose autocorrelation falls to 1/e at ``length_px`` pixels: white noise
    through a Gaussian filter of std length_px / 2 (its autocorrelation is exp(-lag^2 / (4 std^2))), rescaled to
    std 1. ``length_px`` 0: white noise."""
    white = rng.normal(size=shape)
    if length_px <= 0:
        return white
    from scipy.ndimage import gaussian_filter

    field = gaussian_filter(white, length_px / 2.0, mode="reflect")
    return field / max(float(field.std()), 1e-12)


def quantise(z: np.ndarray, model: SensorModel) -> np.ndarray:
    """Depth (...) metres rounded as the device reports it: to steps of disparity (1/z) when the model has
    ``disparity_quantum`` (depth steps of disparity_quantum x z^2), else to ``quantum`` steps of depth; 0 keeps
    the depth as it is."""
    if model.disparity_quantum > 0:
        with np.errstate(divide="ignore"):
            q = np.round(1.0 / z / model.disparity_quantum) * model.disparity_quantum
            return np.where((z > 0) & (q > 0), 1.0 / np.where(q > 0, q, 1.0), 0.0)
    return np.round(z / model.quantum) * model.quantum if model.quantum > 0 else z


def flying_depth(clean: np.ndarray, edge: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """For each ``edge`` pixel, a depth between the nearest and the farthest reading of its 3x3 neighbourhood
    (``clean`` (H, W) metres, 0 = none), drawn uniformly in the middle 60 % of that gap (a flying pixel belongs to
    neither side); other pixels keep their depth. -> (H, W) metres."""
    d = np.where(clean > 0, clean, np.nan)
    pad = np.pad(d, 1, constant_values=np.nan)
    h, w = d.shape
    stack = np.stack([pad[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN window: no reading around, handled below
        near, far = np.nanmin(stack, axis=0), np.nanmax(stack, axis=0)
    t = rng.uniform(0.2, 0.8, size=d.shape)
    return np.where(edge & np.isfinite(near) & np.isfinite(far), near + t * (far - near), clean)


def apply_sensor(depth: np.ndarray, rng: np.random.Generator, model: SensorModel = SensorModel(),
                 K: np.ndarray | None = None) -> np.ndarray:
    """Noisy sensor reading of a noise-free depth image. (H, W) float metres, 0 = none -> (H, W) float32.
    ``K`` (3, 3): the intrinsics, needed by the models whose lengths are angles or that drop grazing pixels.

    Noise is added before quantisation, as in the real device (it measures disparity, then rounds). The
    extensions draw their random numbers after the Kinect-like model's, so that model's output is unchanged.
    """
    clean = np.asarray(depth, dtype=np.float64)
    valid = clean > 0
    needs_K = (model.noise_corr_mrad > 0 or model.slow_corr_mrad > 0 or model.edge_mrad > 0
               or model.grazing_drop > 0 or model.sigma_angle > 0)
    if needs_K and K is None:
        raise ValueError("this sensor model needs the intrinsics K")
    px = (lambda mrad: mrad * 1e-3 * float(K[0, 0])) if K is not None else (lambda mrad: 0.0)
    noise = (correlated_noise(clean.shape, px(model.noise_corr_mrad), rng) if model.noise_corr_mrad > 0
             else rng.normal(size=clean.shape))
    if model.outlier_share > 0:
        noise = noise * np.where(rng.random(clean.shape) < model.outlier_share, model.outlier_scale, 1.0)
    sigma = axial_sigma(clean, model)
    # Incidence (radians, 0 where unknown), computed once for the angular noise and the grazing holes alike.
    angle = (np.nan_to_num(incidence_angle(clean, K, model.edge_jump), nan=0.0)
             if model.sigma_angle > 0 or model.grazing_drop > 0 else None)
    if model.sigma_angle > 0:
        theta = np.minimum(angle, np.radians(model.max_angle_deg))
        sigma = sigma + model.sigma_angle * clean**1.5 * theta**2 / (np.pi / 2 - theta) ** 2
    noisy = clean + noise * sigma
    noisy = quantise(noisy, model)
    width = max(1, int(round(px(model.edge_mrad)))) if model.edge_mrad > 0 else model.edge_width
    edge = discontinuities(clean, model.edge_jump, width)
    drop = (edge & (rng.random(clean.shape) < model.edge_drop)) | (rng.random(clean.shape) < model.random_drop)
    if model.slow_sigma > 0:
        slow = correlated_noise(clean.shape, px(model.slow_corr_mrad), rng) * model.slow_sigma * clean**model.slow_power
        noisy = quantise(noisy + slow, model)
    if model.bias_sigma > 0:
        noisy = quantise(noisy + rng.normal() * model.bias_sigma, model)
    if model.grazing_drop > 0:
        grazing = np.degrees(angle) > model.grazing_deg
        drop |= grazing & (rng.random(clean.shape) < model.grazing_drop)
    if model.flying > 0:
        jumps = discontinuities(clean, model.edge_jump, 1) & (rng.random(clean.shape) < model.flying)
        noisy = np.where(jumps, quantise(flying_depth(clean, jumps, rng) + noise * sigma,
                                         model), noisy)
        drop &= ~jumps
    return np.where(valid & ~drop & (noisy > 0) & (noisy <= model.max_range), noisy, 0.0).astype(np.float32)


# Where each xtion number was measured: `benchmarks/sensor_stats.py ../shared/datasets/ycbv-real-dev` (10 frames,
# 2026-12-06), on the table's and the objects' pixels; "calibrated" ones were then set so that the same script on a
# generated set (make-scenes --sensor xtion) gives the measured statistic, since the generator's own edges and
# resolution (525 px against 1067) change how a parameter shows. See ``sensor_model`` for the presets.
XTION = SensorModel(
    sigma_base=0.0, z_ref=0.0,
    sigma_quad=0.00145,  # fast residual's robust std / z^2 on the table: 1.56, 1.41, 1.42, 1.60, 1.28 mm at 0.87-1.8 m
    sigma_angle=0.0001,  # Nguyen et al.'s angular term as published (0.1 mm); on the objects the fast std rises by
    # 0.12, 0.82, 2.7 mm at 52, 65, 75 degrees of incidence, the term by 0.19, 0.68, 2.5 mm at 1 m
    noise_corr_mrad=6.0,  # fast residual's 1/e length: objects 4.7, table 5.5 mrad (calibrated: 5.0 gave 3.8, 4.5)
    outlier_share=0.035, outlier_scale=3.0,  # beyond 3 robust stds of fast / z^2: table 1.6 %, objects 3.7 %
    # (a normal law: 0.27 %; calibrated: without them the generated set gave 0.6 % and 2.0 %)
    slow_sigma=0.0023, slow_power=3.5,  # slow residual's std on the table: 1.43, 2.28, 4.55 mm at 0.87, 1.02, 1.2 m
    slow_corr_mrad=69.0,  # slow residual's 1/e length on the table
    bias_sigma=0.0,  # median object residual per frame: 0.21-0.54 mm over the 10 frames, spread 0.09 mm (none)
    edge_mrad=3.0, edge_drop=0.47,  # holes within 3 mrad of a silhouette: 46.5 %
    random_drop=0.0093,  # holes elsewhere: 1.1 % (calibrated: 0.011 gave 1.31 %)
    grazing_deg=70.0, grazing_drop=0.21,  # holes beyond 70 degrees of incidence, edges aside: 20.6 %
    flying=0.065,  # readings at edges between the two sides, far from both: 3.9 % (calibrated: 0.04 gave 2.4 %)
    quantum=0.001,  # every millimetre value occurs in the real frames (registered, resampled): no disparity steps
)


def check_sensor(name: str) -> None:
    """InputError unless ``name`` is one of ``SENSOR_NAMES``."""
    if name not in SENSOR_NAMES:
        from workbench.errors import InputError

        raise InputError("--sensor", f"unknown sensor {name!r}; choose from {', '.join(SENSOR_NAMES)}")


def sensor_model(name: SensorName) -> SensorModel:
    """The named sensor: ``ideal`` (no noise, no holes, no steps), ``kinect-like`` (``SensorModel()``) or
    ``xtion`` (``XTION``, measured)."""
    if name == "ideal":
        return replace(SensorModel(), sigma_base=0.0, sigma_quad=0.0, edge_drop=0.0, random_drop=0.0, quantum=0.0)
    if name == "kinect-like":
        return SensorModel()
    if name == "xtion":
        return XTION
    raise ValueError(f"unknown sensor {name!r}; choose from {', '.join(SENSOR_NAMES)}")
