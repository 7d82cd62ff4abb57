"""The estimator's settings: the filter (method, particle count, iterations, Sigma, tempering, convergence) and
the search (proposals, the move mix, the library, coarse to fine, settling)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from workbench.errors import InputError, check_count, is_whole_number
from workbench.inference.search.moves.registry import PROPOSALS, MoveMix
from workbench.inference.smc.particles import STATES, Sigma

METHODS = ("pipf", "mcpf")
MAX_SEED = 2**64 - 1
# Upper bounds of the counts a user gives, each with its reason: beyond them a run is a typo, not a plan.
MAX_PARTICLES = 100_000  # the paper used 1444; a run's memory grows with them (evaluation.pool.check_run_memory)
MAX_ITERATIONS = 10_000  # the search converges within 100 on every frame measured; 10,000 take hours per frame
MAX_SIGMA_M = 1.0  # a diffusion step of more than a metre leaves any table scene
MAX_SIGMA_RAD = 2 * math.pi
MAX_BUDGET_S = 86400.0


def check_seed(seed, where: str = "--seed") -> int:
    """numpy's generators take seeds 0 <= seed < 2**64 here (a negative one would fail only inside a worker)."""
    if not is_whole_number(seed) or not 0 <= seed <= MAX_SEED:
        raise InputError(where, f"the seed must be a whole number from 0 to 2**64-1, got {seed!r}")
    return int(seed)


@dataclass(frozen=True)
class EstimatorConfig:
    method: str = "pipf"
    # As accurate as more particles and iterations on real and generated frames, at a fraction of the time
    # (docs/journal/2026-11.md, "The search, fifth step").
    particles: int = 200
    iterations: int = 20
    sigma: Sigma = field(default_factory=Sigma)
    state: str = "6dof"
    seed: int = 0
    # "paper": random starts and Gaussian diffusion only, as Desingh et al. define PI-PF and PI-MCPF; "default":
    # data-driven starts and the move mix below (inference/), with Sigma shrinking as the particles agree.
    proposals: str = "default"
    moves: MoveMix = field(default_factory=MoveMix)
    data_start: float = 0.8  # share of objects in the initial particles drawn from data-driven candidates
    # With the clutter floor on (``LikelihoodConfig.clutter_floor``): the share of the iterations weighed without
    # it. The plain mixture makes an object's readings pull it hard (an unexplained reading is an outlier, about
    # -3.4, not the floor's 2), so the search first puts every object on readings it explains, and the floor then
    # decides between what it found and the scenes that leave clutter to itself (docs/journal/2026-11.md, "The floor
    # weighed in halfway").
    floor_from: float = 0.5
    # The floor also comes in once the estimate has been calm (``converge_position``, ``converge_degrees``) for this
    # many iterations without it (None: only at ``floor_from``): the search has put every object on readings it
    # explains, and waiting for ``floor_from`` repeats what it found (docs/journal/2026-12.md, "The floor in once
    # calm").
    floor_calm: int | None = 3
    library_every: int = 2  # iterations between refits of the candidates to what the estimate leaves unexplained
    sigma_floor: float = 0.25  # coarse to fine: Sigma shrinks per object down to this fraction
    target_ess: float = 0.25  # fraction of N kept by the tempered weights each iteration
    converge_position: float = 0.01  # m; the paper's "best particle moves < 1 cm"
    converge_degrees: float = 3.0  # and "< 3 degrees"
    # Consecutive iterations the rule must hold, with the clutter floor in. Half of the iterations after the floor
    # came in, at the default 20: with the floor in once calm, ten more repeat what the first five found on the
    # real frames (docs/journal/2026-12.md, "The floor in once calm"). PI-MCPF keeps its best particle whenever
    # the proposals around it are rejected, so the paper's tables, measured with 10, keep 10 (``bench.tables``).
    converge_patience: int = 5
    # Settling (inference.answer.settle): the estimate is fitted to the depth without physics at the end of a run, each
    # object within this far (m) and this turn (deg) of where physics put it, and each object's half turns are
    # tried; 0 turns it off, as do the paper's proposals. Physics rests an object a little off where its depth puts
    # it; a tighter region holds objects at its edge, a wider one lets settled scenes stop being restful under
    # physics (docs/journal/2026-11.md, "Settling" and "Settling, third step").
    settle_shift: float = 0.015
    settle_turn: float = 12.0
    # Leaning starts (inference.search.leaning): every object laid along each slanted flat patch of the observed
    # points, the best of each patch tried by polish while the estimate is stuck, never drawn into particles: a real
    # desk's clutter shows slanted patches, and drawn into particles they send the search astray
    # (docs/journal/2026-11.md, "Leaning starts").
    leaning: bool = True
    # Anytime: the run's wall seconds (None: until converged or the iterations end). The iterations stop at
    # ``clock.ITERATE_SHARE`` of it, and the answer's stages that do not fit are skipped, which the posterior says
    # (``Posterior.cut_short``). A run always makes its start and its answer from it, so a budget shorter than the
    # start is overrun by it.
    budget_s: float | None = None

    def validate(self, where: str | None = None) -> None:
        """InputError naming the first setting at fault. Settings a user gave (``where`` not None: "" on the command
        line, whose flags name them, or the prefix of their names in a file, e.g. ``estimator_config.``) are also
        held to the bounds of a run: the seed numpy takes, whole counts, a diffusion that stays on a table."""
        if self.method not in METHODS:
            raise InputError("method", f"unknown method {self.method!r}; use one of {', '.join(METHODS)}")
        if self.state not in STATES:
            raise InputError("state", f"unknown state {self.state!r}; use one of {', '.join(STATES)}")
        if not 1 <= self.particles <= MAX_PARTICLES:
            named = "particles" if where is None else f"{where}particles" if where else "--particles"
            raise InputError(named, f"particle count must be between 1 and {MAX_PARTICLES}, got {self.particles}")
        if self.iterations < 0:
            raise InputError("iterations", f"iterations must be >= 0, got {self.iterations}")
        if self.proposals not in PROPOSALS:
            raise InputError("proposals", f"unknown proposals {self.proposals!r}; use one of {', '.join(PROPOSALS)}")
        self.moves.validate()
        for name in ("data_start", "sigma_floor", "floor_from"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InputError(name, f"must lie in [0, 1], got {getattr(self, name)}")
        if self.floor_calm is not None and self.floor_calm < 1:
            raise InputError("floor_calm", f"must be >= 1, got {self.floor_calm}")
        if self.library_every < 1:
            raise InputError("library_every", f"must be >= 1, got {self.library_every}")
        for name in ("settle_shift", "settle_turn"):
            if not (getattr(self, name) >= 0.0 and np.isfinite(getattr(self, name))):
                raise InputError(name, f"must be a finite number >= 0, got {getattr(self, name)}")
        if not 0.0 < self.target_ess <= 1.0:
            raise InputError("target_ess", f"must lie in (0, 1], got {self.target_ess}")
        self.sigma.validate()
        if self.budget_s is not None and not (np.isfinite(self.budget_s) and 0 < self.budget_s <= MAX_BUDGET_S):
            raise InputError("--budget" if where == "" else f"{where or ''}budget_s",
                             f"the budget must be a number of seconds above 0 and at most {MAX_BUDGET_S:g} "
                             f"(a day), got {self.budget_s}")
        if where is None:
            return
        check_seed(self.seed, f"{where}seed" if where else "--seed")
        check_count(self.iterations, f"{where}iterations" if where else "--iterations", low=0, high=MAX_ITERATIONS)
        check_count(self.particles, f"{where}particles" if where else "--particles", high=MAX_PARTICLES)
        sigma = np.asarray(self.sigma.as_array(), dtype=np.float64)  # x, y, z metres; roll, pitch, yaw radians
        if np.any(sigma[:3] > MAX_SIGMA_M) or np.any(sigma[3:] > MAX_SIGMA_RAD):
            raise InputError(f"{where}sigma", f"diffusion must be at most {MAX_SIGMA_M:g} m and 360 degrees per "
                                              f"iteration, got {sigma.tolist()}")
