"""The paper's search (``--proposals paper``): PI-PF / PI-MCPF exactly as Desingh et al. publish them, behind
the filter core's ``filter.Search`` hooks. ``default_search.DefaultSearch`` is the data-driven one."""

from __future__ import annotations

import time
from collections.abc import Iterable

import numpy as np

from workbench.inference.search.moves import gaussian
from workbench.inference.search.moves.registry import MoveKind
from workbench.inference.smc.filter import (
    ParticleFilter,
    Proposed,
    Settled,
    Started,
    Update,
)
from workbench.inference.smc.particles import initial_particles


class PaperSearch:
    """Desingh et al.'s PI-PF / PI-MCPF: uniformly random starts over the object region, joint Gaussian diffusion
    with Sigma (the x, y, z, yaw state for clutter when ``state`` is "xyzyaw"), the projected estimate returned."""

    def start(self, filt: ParticleFilter) -> Started:
        cfg, problem = filt.config, filt.problem
        start = initial_particles(filt.rng, cfg.particles, problem.models, problem.table, cfg.state)
        return Started(start, np.full(cfg.particles, int(MoveKind.START), np.int8))

    def propose(self, filt: ParticleFilter, parents: np.ndarray) -> Proposed:
        cfg, n = filt.config, len(parents)
        hypotheses = gaussian.propose_joint(filt.rng, parents, cfg.sigma, np.ones(filt.problem.n_objects),
                                            cfg.state).hypotheses
        t0 = time.perf_counter()
        ev = filt.evaluate(hypotheses)
        return Proposed(hypotheses, np.zeros(n), np.full(n, int(MoveKind.JOINT), np.int8), ev,
                        time.perf_counter() - t0)

    def after_step(self, filt: ParticleFilter) -> Iterable[Update]:
        return ()

    def finish(self, filt: ParticleFilter) -> Settled:
        return Settled(filt.estimated_scene.copy(), filt.estimate_loglik)

    def state_dict(self) -> dict:
        """Nothing: the paper's search remembers nothing between steps."""
        return {}

    def load_state(self, search: dict) -> None:
        pass
