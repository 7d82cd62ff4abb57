"""Physics projection (PI-PF): each hypothesis is simulated in Bullet until it is at rest.

- ``projector``: ``PhysicsProjector`` simulates hypotheses to rest (``PhysicsConfig`` says how) and reports how
  each ended (the ``STATUS_*`` codes);
- ``collision``: what each object collides as, the simplest shape whose measured fit is good enough;
- ``bullet``: pybullet, imported without the line it prints.

Callers import the projector's names from here: ``from workbench.physics import PhysicsProjector``.
"""

from workbench.physics.projector import (
    STATUS_AS_GIVEN, STATUS_NAMES, STATUS_OFF_TABLE, STATUS_OUTSIDE, STATUS_REST, STATUS_STEP_CAP, STATUS_UNSTABLE,
    PhysicsConfig, PhysicsProjector, collision_shapes,
)

__all__ = [
    "STATUS_AS_GIVEN", "STATUS_NAMES", "STATUS_OFF_TABLE", "STATUS_OUTSIDE", "STATUS_REST", "STATUS_STEP_CAP",
    "STATUS_UNSTABLE", "PhysicsConfig", "PhysicsProjector", "collision_shapes",
]
