"""The settings of ``workbench track``: a tracked frame's short search, lost tracking, the camera's motion."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from workbench.errors import InputError
from workbench.inference.config import EstimatorConfig
from workbench.inference.search.moves.registry import MOVES, MoveMix
from workbench.inference.smc.particles import Sigma

MOTIONS = ("auto", "given", "depth")


def _only(**shares: float) -> MoveMix:
    """A move mix of the named kinds only."""
    return MoveMix(**{**{m.name: 0.0 for m in MOVES}, **shares})


@dataclass(frozen=True)
class TrackConfig:
    """A tracked frame runs ``iterations`` of ``particles`` from the carried particle set, with local moves
    (``moves``) of a small ``sigma``: the objects stand still, only the camera's motion is uncertain (a few mm and a
    degree). No ICP among them: the frame's settle fits each object to the depth after the step anyway, and ICP
    refits are computed in this process while the workers wait. Few particles, for the same reason: the settle,
    not the step, places each object. Objects found lost are re-searched with ``lost_iterations`` of
    ``re_search_particles`` and ``lost_moves`` (data-driven moves added): there the particles search.
    ``lost_badness``, ``lost_rise``: an object is lost when its carried pose's badness
    (``scenepoints.object_badness``) on the new frame exceeds both ``lost_badness`` and its badness on the previous
    frame plus ``lost_rise``. More than ``reinit_share`` of the objects lost: the frame is estimated from scratch.
    A frame whose depth has readings on less than ``min_depth_share`` of its pixels (a dropped or blanked frame) is
    lost as a whole: nothing is searched, the posterior is carried through it unchanged. ``motion``: the camera's
    motion from ``scene_camera_world.json`` (given), from the depth, or given where the scene has the file
    (auto)."""

    particles: int = 30
    iterations: int = 1
    sigma: Sigma = field(default_factory=lambda: Sigma(0.003, 0.003, 0.002, *np.radians([1.5, 1.5, 2.0])))
    moves: MoveMix = field(default_factory=lambda: _only(joint=0.4, single=0.6))
    lost_particles: int = 60
    lost_iterations: int = 6
    lost_moves: MoveMix = field(default_factory=lambda: _only(joint=0.15, single=0.3, icp=0.2, data=0.3, turn=0.05))
    lost_badness: float = 0.35
    lost_rise: float = 0.2
    reinit_share: float = 0.5
    min_depth_share: float = 0.05
    motion: str = "auto"

    def validate(self) -> None:
        if self.motion not in MOTIONS:
            raise InputError("--motion", f"unknown {self.motion!r}; use one of {', '.join(MOTIONS)}")
        for name in ("particles", "iterations", "lost_particles", "lost_iterations"):
            if getattr(self, name) < 1:
                raise InputError(name, f"must be >= 1, got {getattr(self, name)}")
        for name in ("lost_badness", "lost_rise", "reinit_share", "min_depth_share"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InputError(name, f"must lie in [0, 1], got {getattr(self, name)}")

    @property
    def re_search_particles(self) -> int:
        """Particles of a frame that re-searches lost objects: ``lost_particles``, or ``particles`` if more."""
        return max(self.particles, self.lost_particles)

    def frame_config(self, config: EstimatorConfig, lost: bool) -> EstimatorConfig:
        """The estimator's settings for a tracked frame, from the run's ``config`` (its seed, method, state and
        settling kept): re-searching lost objects (``lost``) or not. A frame that is only tracked weighs the clutter
        floor in from its first step: the carried particles already rest on their readings."""
        return replace(config, particles=self.re_search_particles if lost else self.particles, sigma=self.sigma,
                       iterations=self.lost_iterations if lost else self.iterations,
                       moves=self.lost_moves if lost else self.moves,
                       floor_from=config.floor_from if lost else 0.0)
