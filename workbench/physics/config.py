"""How the physics projection simulates a hypothesis to rest: ``PhysicsConfig``, checked on construction."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from workbench.errors import InputError
from workbench.physics.collision import KINDS

BACKENDS = ("pybullet", "mujoco")


@dataclass(frozen=True)
class PhysicsConfig:
    """How a hypothesis is simulated to rest. Defaults chosen by measurement (benchmarks/physics_speed.py).

    The particle is at rest when every object's speeds stay below ``rest_linear`` (m/s) and ``rest_angular``
    (rad/s) at ``rest_checks`` consecutive checks, made every ``check_every`` steps. An object whose centre of mass
    drops below ``off_table_z`` has fallen off the table; a speed above ``max_speed`` (m/s) or ``max_angular``
    (rad/s), or a centre more than ``max_distance`` beyond the table's edges or above it, means the simulation blew
    up. Before simulating, penetrations deeper than ``penetration_tolerance`` are pushed apart in up to
    ``separation_iterations`` passes. ``table_friction`` multiplies each object's own friction: Bullet's combined
    friction is the product of the two. ``rolling_friction`` (m) and ``spinning_friction`` (m) of the objects
    resist rolling and turning in place (Bullet limits the contact torque to about them times the normal force,
    combined as r_a * f_b + r_b * f_a with the lateral frictions f): without them a can or marker on its side
    rolls on for as long as it is simulated.
    ``linear_damping`` and ``angular_damping`` are Bullet's velocity damping (the fraction of speed lost per
    second). ``solver_residual``: the contact solver stops iterating below it; ``cone_friction``: Bullet's cone
    friction instead of its pyramid. ``shape_overrides``:
    (obj_id, kind) pairs forcing an object's collision shape kind (see ``collision``). ``sleep_calm``: a body at rest
    by the test above sleeps (Bullet skips it) until a moving body touches it; see ``PhysicsProjector._simulate``.
    ``backend``: the simulator, Bullet ("pybullet", ``PhysicsProjector``) or MuJoCo ("mujoco", ``MujocoProjector``,
    which leaves ``solver_residual`` and ``sleep_calm`` to Bullet); ``physics.make_projector`` builds its projector.
    """

    # 1/120 s with 30 solver iterations settles a 4-box particle in half the time of 1/240 s with 60, with
    # rest poses within ~1 mm (median; 3.5 mm p90) of those: well inside the filter's 1 cm diffusion.
    timestep: float = 1.0 / 120.0
    solver_iterations: int = 30
    max_steps: int = 300
    # Measured on real meshes (benchmarks/real_physics.py): half these thresholds costs 20 % more steps for the
    # same resting poses against the unsimplified shapes.
    rest_linear: float = 0.02
    rest_angular: float = 0.2
    check_every: int = 4
    rest_checks: int = 2
    gravity: float = 9.81
    table_thickness: float = 0.05
    table_friction: float = 0.75
    off_table_z: float = -0.1
    max_speed: float = 10.0
    max_angular: float = 100.0
    max_distance: float = 2.0
    penetration_tolerance: float = 5e-4
    separation_iterations: int = 10
    # The solver stops iterating once its residual is below this: a third off the cost of a step on real meshes,
    # resting poses within 0.1 mm (median) of Bullet's default 1e-7 (benchmarks/real_physics.py). Bullet's
    # pyramid friction would save another quarter, but moved true resting scenes twice as far from those with
    # the unsimplified shapes (benchmarks/true_scene_drift.py --reference: median 3.1 mm against 1.4).
    solver_residual: float = 1e-4
    cone_friction: bool = True
    rolling_friction: float = 0.002
    spinning_friction: float = 0.002
    linear_damping: float = 0.04
    angular_damping: float = 0.04
    shape_overrides: tuple[tuple[int, str], ...] = ()
    sleep_calm: bool = True
    backend: Literal["pybullet", "mujoco"] = "pybullet"

    def __post_init__(self):
        positive = ("timestep", "solver_iterations", "solver_residual", "max_steps", "rest_linear", "rest_angular",
                    "check_every", "rest_checks", "table_thickness", "max_speed", "max_angular", "max_distance",
                    "penetration_tolerance", "separation_iterations")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"PhysicsConfig.{name}", f"must be a positive finite number, got {value!r}")
        for obj_id, kind in self.shape_overrides:
            if kind not in KINDS:
                raise InputError("PhysicsConfig.shape_overrides",
                                 f"object {obj_id}: kind must be one of {', '.join(KINDS)}, not {kind!r}")
        for name in ("gravity", "table_friction", "rolling_friction", "spinning_friction", "linear_damping",
                     "angular_damping"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"PhysicsConfig.{name}", f"must be a finite number >= 0, got {value!r}")
        if self.backend not in BACKENDS:
            raise InputError("PhysicsConfig.backend", f"must be one of {', '.join(BACKENDS)}, not {self.backend!r}")
        if not (math.isfinite(self.off_table_z) and self.off_table_z < 0):
            raise InputError("PhysicsConfig.off_table_z",
                             f"must be below the table top (< 0), got {self.off_table_z!r}")
