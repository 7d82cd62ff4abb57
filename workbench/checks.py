"""Checks of user-given settings and poses, shared by the command line, the app and session files, so that an
impossible value is refused (``InputError``) before anything is loaded or started, wherever it came from.

- ``check_workers``: 1 <= workers <= ``max_workers()``, a bound from this machine's cores and free memory.
- ``check_seed``: numpy's generators take seeds 0 <= seed < 2**64 here (a negative one fails inside a worker).
- ``check_estimator_config`` / ``check_problem_config``: the dataclasses' own ``validate`` plus bounds they lack.
- ``check_rigid``: poses (..., 4, 4) must be rigid (rotation orthonormal with det +1, bottom row 0 0 0 1):
  a reflection would otherwise be turned silently into some other pose by the quaternion conversion.
"""

from __future__ import annotations

import math
import os

import numpy as np

from workbench.errors import InputError

# Memory one evaluation worker needs: docs/benchmarks.md's speed table measured 433 MB peak per worker (4 objects, 1444
# particles); the rest is headroom for larger meshes and the main process's share.
WORKER_MEMORY_BYTES = 600 * 2**20
MAX_SEED = 2**64 - 1
MAX_SIGMA_M = 1.0  # a diffusion step of more than a metre leaves any table scene
MAX_SIGMA_RAD = 2 * math.pi
# Rotation and bottom-row tolerance of a rigid pose: files store rotations with ~6 digits, products of many
# rotations drift by ~1e-12.
RIGID_TOLERANCE = 1e-3


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def available_memory() -> int | None:
    """Bytes of memory available to new processes (Linux MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def max_workers() -> int:
    """The most evaluation workers worth starting here: one per usable core, and no more than the available
    memory holds at ``WORKER_MEMORY_BYTES`` each (at least 1)."""
    bound = usable_cores()
    memory = available_memory()
    if memory is not None:
        bound = min(bound, memory // WORKER_MEMORY_BYTES)
    return max(1, int(bound))


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def check_workers(workers, where: str = "--workers") -> int:
    """``workers`` if 1 <= workers <= max_workers(), else InputError saying the bound and why."""
    bound = max_workers()
    if not _is_int(workers) or not 1 <= workers <= bound:
        memory = available_memory()
        free = "" if memory is None else f", {memory / 2**30:.1f} GiB free"
        raise InputError(where, f"evaluation workers must be a whole number from 1 to {bound} on this machine "
                                f"({usable_cores()} cores{free}, ~{WORKER_MEMORY_BYTES // 2**20} MB per worker), "
                                f"got {workers!r}")
    return int(workers)


def check_seed(seed, where: str = "--seed") -> int:
    if not _is_int(seed) or not 0 <= seed <= MAX_SEED:
        raise InputError(where, f"the seed must be a whole number from 0 to 2**64-1, got {seed!r}")
    return int(seed)


def check_count(value, where: str, low: int = 1, high: int | None = None) -> int:
    """A whole-number setting within [low, high]."""
    if not _is_int(value) or value < low or (high is not None and value > high):
        span = f"from {low} to {high}" if high is not None else f">= {low}"
        raise InputError(where, f"must be a whole number {span}, got {value!r}")
    return int(value)


def check_estimator_config(config, where: str = "") -> None:
    """``EstimatorConfig.validate`` plus the seed and the diffusion's plausible range. ``where`` prefixes the
    names of settings (e.g. ``estimator_config.`` for a session file)."""
    config.validate()
    check_seed(config.seed, f"{where}seed" if where else "--seed")
    check_count(config.iterations, f"{where}iterations" if where else "--iterations", low=0)
    check_count(config.particles, f"{where}particles" if where else "--particles", high=100_000)
    sigma = np.asarray(config.sigma.as_array(), dtype=np.float64)  # x, y, z metres; roll, pitch, yaw radians
    if np.any(sigma[:3] > MAX_SIGMA_M) or np.any(sigma[3:] > MAX_SIGMA_RAD):
        raise InputError(f"{where}sigma", f"diffusion must be at most {MAX_SIGMA_M:g} m and 360 degrees per "
                                          f"iteration, got {sigma.tolist()}")


# Upper bounds of the physics and render settings a session file may carry: beyond them a step never ends (a
# simulation that may run 10**30 steps) or pybullet and OpenGL overflow their C integers.
PHYSICS_MAX = {"timestep": 0.1, "solver_iterations": 10_000, "max_steps": 100_000, "check_every": 10_000,
               "rest_checks": 10_000, "separation_iterations": 10_000, "rest_linear": 100.0, "rest_angular": 1000.0,
               "table_thickness": 10.0, "max_speed": 1e4, "max_angular": 1e5, "max_distance": 1e3,
               "penetration_tolerance": 1.0, "gravity": 1e3, "table_friction": 100.0}
RENDER_BACKENDS = ("auto", "osmesa", "egl")
MAX_FRAMEBUFFER = 16384


def check_problem_config(config, where: str = "") -> None:
    """What ``problem.problem.build_problem`` would refuse only after the frame is loaded, and the bounds of the physics
    and render settings (``PhysicsConfig`` checks only their signs). ``where`` prefixes the settings' names."""
    config.likelihood.validate()
    lik = config.likelihood
    for name in ("sigma", "depth_range", "max_residual"):  # metres; squared and divided by, so not too small
        value = getattr(lik, name)
        if not (isinstance(value, (int, float)) and 1e-6 <= value <= 1e3):
            raise InputError(f"{where}likelihood.{name}", f"must be from 1e-6 to 1000 metres, got {value!r}")
    check_count(config.max_render_pixels, f"{where}max_render_pixels" if where else "--max-render-pixels", low=64)
    check_count(config.min_object_pixels, f"{where}min_object_pixels", low=0)
    for name, high in PHYSICS_MAX.items():
        value = getattr(config.physics, name)
        if not value <= high:
            raise InputError(f"{where}physics.{name}", f"must be at most {high:g}, got {value!r}")
    if not config.physics.off_table_z >= -1e3:
        raise InputError(f"{where}physics.off_table_z", f"must be at least -1000, got {config.physics.off_table_z!r}")
    if config.render.backend not in RENDER_BACKENDS:
        raise InputError(f"{where}render.backend", f"must be one of {', '.join(RENDER_BACKENDS)}, got "
                                                   f"{config.render.backend!r}")
    check_count(config.render.max_framebuffer, f"{where}render.max_framebuffer", low=64, high=MAX_FRAMEBUFFER)


def check_rigid(T, what: str, path=None) -> np.ndarray:
    """Poses (..., 4, 4) -> float64 copy, or InputError(path, ...) naming ``what`` when a pose is not finite,
    its rotation is not orthonormal with determinant +1 (a reflection), or its bottom row is not 0 0 0 1."""
    try:
        T = np.array(T, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(path, f"{what}: poses must be 4x4 matrices of numbers") from e
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise InputError(path, f"{what}: poses must be 4x4 matrices, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise InputError(path, f"{what}: a pose contains NaN or inf")
    if np.abs(T[..., 3, :] - [0.0, 0.0, 0.0, 1.0]).max(initial=0.0) > RIGID_TOLERANCE:
        raise InputError(path, f"{what}: the bottom row of a pose must be [0, 0, 0, 1]")
    R = T[..., :3, :3]
    # Entries of a rotation lie in [-1, 1]: checked first so that huge values are refused without overflowing.
    if np.abs(R).max(initial=0.0) > 1 + RIGID_TOLERANCE or \
            np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(initial=0.0) > RIGID_TOLERANCE:
        raise InputError(path, f"{what}: a rotation is not orthonormal")
    if np.any(np.linalg.det(R) < 0):
        raise InputError(path, f"{what}: a rotation has determinant -1 (a reflection, not a rotation)")
    return T
