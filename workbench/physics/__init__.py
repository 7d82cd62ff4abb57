"""Physics projection (PI-PF): each hypothesis is simulated in Bullet until it is at rest.

- ``projector``: ``PhysicsProjector`` separates a hypothesis's objects, simulates them to rest and reports how
  each simulation ended (the ``STATUS_*`` codes);
- ``world``: the Bullet world it simulates in (table, bodies at their centres of mass), reused for every particle
  without a particle's result depending on the ones before;
- ``config``: ``PhysicsConfig``, how a hypothesis is simulated to rest;
- ``collision``: what each object collides as, the simplest shape whose measured fit is good enough;
- ``bullet``: pybullet, imported without the line it prints.

Callers import the projector's names from here: ``from workbench.physics import PhysicsProjector``.
"""

from workbench.physics.config import PhysicsConfig
from workbench.physics.projector import (
    STATUS_AS_GIVEN,
    STATUS_NAMES,
    STATUS_OFF_TABLE,
    STATUS_OUTSIDE,
    STATUS_REST,
    STATUS_STEP_CAP,
    STATUS_UNSTABLE,
    PhysicsProjector,
    collision_shapes,
)

__all__ = [
    "STATUS_AS_GIVEN", "STATUS_NAMES", "STATUS_OFF_TABLE", "STATUS_OUTSIDE", "STATUS_REST", "STATUS_STEP_CAP",
    "STATUS_UNSTABLE", "PhysicsConfig", "PhysicsProjector", "collision_shapes",
]
