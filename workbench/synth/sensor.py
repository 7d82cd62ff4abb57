"""A Kinect-like depth sensor model applied to noise-free synthetic depth.

Axial noise follows Nguyen, Izadi & Lovell (2012), "Modeling Kinect Sensor Noise for Improved 3D Reconstruction
and Tracking": sigma(z) = 1.2 mm + 1.9 mm * (z - 0.4 m)^2 / m^2. Structured-light sensors also lose readings
where the depth jumps (the projector's pattern is shadowed or smeared there) and at scattered pixels, and they
report depth in millimetre steps, up to a maximum range (OpenNI drops Kinect v1 readings beyond about 6 m, where
a large desk seen at a grazing angle lets the view reach the far floor).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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


def apply_sensor(depth: np.ndarray, rng: np.random.Generator, model: SensorModel = SensorModel()) -> np.ndarray:
    """Noisy sensor reading of a noise-free depth image. (H, W) float metres, 0 = none -> (H, W) float32.

    Noise is added before quantisation, as in the real device (it measures disparity, then rounds).
    """
    clean = np.asarray(depth, dtype=np.float64)
    valid = clean > 0
    noisy = clean + rng.normal(size=clean.shape) * axial_sigma(clean, model)
    noisy = np.round(noisy / model.quantum) * model.quantum
    edge = discontinuities(clean, model.edge_jump, model.edge_width)
    drop = (edge & (rng.random(clean.shape) < model.edge_drop)) | (rng.random(clean.shape) < model.random_drop)
    return np.where(valid & ~drop & (noisy > 0) & (noisy <= model.max_range), noisy, 0.0).astype(np.float32)
