"""Physics projection (PI-PF): each hypothesis is simulated in Bullet (default) or MuJoCo until it is at rest.

- ``projector``: the interface every backend offers (``Projector``: separate a hypothesis's objects, simulate them
  to rest, report how each simulation ended, the ``STATUS_*`` codes) and Bullet's ``PhysicsProjector``;
- ``world``: the Bullet world it simulates in (table, bodies at their centres of mass), reused for every particle
  without a particle's result depending on the ones before;
- ``mujoco_projector`` and ``mujoco_model``: ``MujocoProjector``, the same projection in MuJoCo (the optional
  ``mujoco`` package), and the MJCF model it simulates;
- ``bodies``: each body's frame (centre of mass, principal axes), the same in both backends;
- ``config``: ``PhysicsConfig``, how a hypothesis is simulated to rest, and in which backend;
- ``collision``: what each object collides as, the simplest shape whose measured fit is good enough;
- ``bullet``: pybullet, imported without the line it prints.

Callers build a projector with ``make_projector``, which picks the backend ``PhysicsConfig.backend`` names.
"""

import os

from workbench.physics.collision import CollisionShape
from workbench.physics.config import BACKENDS, PhysicsConfig
from workbench.physics.mujoco_projector import MujocoProjector, require_mujoco
from workbench.physics.projector import (
    STATUS_AS_GIVEN,
    STATUS_NAMES,
    STATUS_OFF_TABLE,
    STATUS_OUTSIDE,
    STATUS_REST,
    STATUS_STEP_CAP,
    STATUS_UNSTABLE,
    PhysicsProjector,
    Projector,
    collision_shapes,
)
from workbench.problem.scene import ObjectModel, Table


def make_projector(models: list[ObjectModel], table: Table, config: PhysicsConfig = PhysicsConfig(),
                   shapes: list[CollisionShape] | None = None,
                   cache_dir: str | os.PathLike | None = None) -> Projector:
    """The projector of ``config.backend`` for ``models`` on ``table``; ``shapes`` and ``cache_dir`` as
    ``PhysicsProjector``'s. InputError naming the package when MuJoCo is asked for and not installed."""
    cls = MujocoProjector if config.backend == "mujoco" else PhysicsProjector
    return cls(models, table, config, shapes=shapes, cache_dir=cache_dir)


def check_backend(config: PhysicsConfig) -> None:
    """InputError, before any work, when ``config.backend`` needs a package that is not installed."""
    if config.backend == "mujoco":
        require_mujoco()

__all__ = [
    "BACKENDS", "STATUS_AS_GIVEN", "STATUS_NAMES", "STATUS_OFF_TABLE", "STATUS_OUTSIDE", "STATUS_REST",
    "STATUS_STEP_CAP", "STATUS_UNSTABLE", "MujocoProjector", "PhysicsConfig", "PhysicsProjector", "Projector",
    "check_backend", "collision_shapes", "make_projector",
]
