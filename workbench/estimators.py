"""PI-PF and PI-MCPF: physics-informed particle filters over scene hypotheses.

One ``Estimator.step()`` is one iteration:
- PI-PF: resample the projected particles by their tempered likelihood, diffuse them with Sigma, evaluate (project
  to rest, render, weigh).
- PI-MCPF: resample, then one Metropolis-Hastings move per particle: propose X* ~ N(X, Sigma), project and weigh X*,
  accept with probability min(1, L(X*)/L(X)) (in log space, with the same tempering as the weights).
Both evaluate N hypotheses per iteration, so their costs compare one to one. Iteration 0 is the random start.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from workbench.errors import InputError
from workbench.evaluation import STAGES, Evaluation, Evaluator
from workbench.geometry import rotation_angle
from workbench.particles import STATES, Sigma, diffuse, initial_particles, random_relocations, random_turns
from workbench.problem import Problem
from workbench.resampling import ess, normalised_weights, systematic_resample, temper_to_ess

METHODS = ("pipf", "mcpf")


@dataclass(frozen=True)
class EstimatorConfig:
    method: str = "pipf"
    particles: int = 400
    iterations: int = 60
    sigma: Sigma = field(default_factory=Sigma)
    state: str = "6dof"
    seed: int = 0
    target_ess: float = 0.25  # fraction of N kept by the tempered weights each iteration
    turn_prob: float = 0.05  # per object and iteration: a random new heading / face (particles.random_turns)
    relocate_prob: float = 0.02  # per object and iteration: a random new place (particles.random_relocations)
    converge_position: float = 0.01  # m; the paper's "best particle moves < 1 cm"
    converge_degrees: float = 3.0  # and "< 3 degrees"
    # Consecutive iterations the rule must hold. PI-MCPF keeps its best particle whenever the proposals around it
    # are rejected, so a short patience stops it long before the particle set has settled.
    converge_patience: int = 10

    def validate(self) -> None:
        if self.method not in METHODS:
            raise InputError("method", f"unknown method {self.method!r}; use one of {', '.join(METHODS)}")
        if self.state not in STATES:
            raise InputError("state", f"unknown state {self.state!r}; use one of {', '.join(STATES)}")
        if not 1 <= self.particles <= 100_000:
            raise InputError("particles", f"particle count must be between 1 and 100000, got {self.particles}")
        if self.iterations < 0:
            raise InputError("iterations", f"iterations must be >= 0, got {self.iterations}")
        for name in ("turn_prob", "relocate_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InputError(name, f"must lie in [0, 1], got {getattr(self, name)}")
        if not 0.0 < self.target_ess <= 1.0:
            raise InputError("target_ess", f"must lie in (0, 1], got {self.target_ess}")
        self.sigma.validate()


@dataclass
class IterationReport:
    iteration: int
    best_loglik: float
    mean_loglik: float
    ess: float
    beta: float  # likelihood tempering exponent used for this iteration's weights
    best_move_m: float  # how far the best scene moved since the last iteration (max over objects)
    best_move_deg: float
    converged: bool
    n_failed: int  # particles whose physics blew up or left the table
    accept_rate: float  # PI-MCPF only (nan for PI-PF)
    timings: dict[str, float]

    def as_dict(self) -> dict:
        return asdict(self)


def symmetric_angle(problem: Problem, A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Per object, the rotation angle (rad) between scenes A and B (K, 4, 4), up to each model's symmetries -> (K,)."""
    out = np.empty(len(problem.models))
    for k, model in enumerate(problem.models):
        rel = A[k, :3, :3].T @ B[k, :3, :3]  # (3, 3)
        out[k] = rotation_angle(rel[None] @ model.symmetries[:, :3, :3]).min()
    return out


class Estimator:
    """Holds the particle set and steps it. Arrays: ``hypotheses`` (N, K, 4, 4) as proposed, ``projected``
    (N, K, 4, 4) after physics, ``loglik`` (N,), ``status`` (N,); all in the table frame."""

    def __init__(self, problem: Problem, config: EstimatorConfig, evaluator: Evaluator):
        config.validate()
        self.problem = problem
        self.config = config
        self.evaluator = evaluator
        self.rng = np.random.default_rng(config.seed)
        self.iteration = -1
        self.hypotheses = self.projected = self.loglik = self.status = None
        self.history: list[IterationReport] = []
        self.best_history: list[np.ndarray] = []
        self._beta = 1.0
        self._calm = 0

    def set_config(self, config: EstimatorConfig) -> None:
        """Takes effect at the next step; the particle set is kept (its size changes at the next resampling)."""
        config.validate()
        self.config = replace(config, seed=self.config.seed)

    @property
    def best_index(self) -> int:
        return int(np.argmax(self.loglik))

    @property
    def best(self) -> np.ndarray:
        """The most likely scene (K, 4, 4), table frame."""
        return self.projected[self.best_index]

    @property
    def converged(self) -> bool:
        return self._calm >= self.config.converge_patience

    def weights(self) -> np.ndarray:
        """(N,) normalised weights of the current particles, with this iteration's tempering."""
        return normalised_weights(self._beta * self.loglik)

    def step(self) -> IterationReport:
        cfg = self.config
        t0 = time.perf_counter()
        accept_rate = float("nan")
        if self.iteration < 0:
            start = initial_particles(self.rng, cfg.particles, self.problem.models, self.problem.table, cfg.state)
            t_resample = time.perf_counter() - t0
            ev = self.evaluator.evaluate(start)
            self._adopt(start, ev, np.ones(cfg.particles, bool))
        else:
            idx = systematic_resample(self._beta * self.loglik, self.rng, cfg.particles)
            parents = self.projected[idx]
            proposals = self._propose(parents)
            t_resample = time.perf_counter() - t0
            ev = self.evaluator.evaluate(proposals)
            if cfg.method == "pipf":
                self._adopt(proposals, ev, np.ones(len(idx), bool))
            else:
                log_ratio = self._beta * (ev.loglik - self.loglik[idx])
                with np.errstate(invalid="ignore"):
                    accept = np.log(self.rng.random(len(idx))) < np.nan_to_num(log_ratio, nan=-np.inf)
                accept_rate = float(accept.mean())
                self._keep_parents(idx)
                self._adopt(proposals, ev, accept)
        self.iteration += 1
        self._beta = temper_to_ess(self.loglik, cfg.target_ess)
        report = self._report(ev, t_resample, time.perf_counter() - t0, accept_rate)
        self.history.append(report)
        return report

    def run(self, iterations: int | None = None, stop_on_convergence: bool = True, callback=None) -> np.ndarray:
        """Step until ``iterations`` (default: the config's) or convergence -> the best scene (K, 4, 4)."""
        total = self.config.iterations if iterations is None else iterations
        while self.iteration < total:
            report = self.step()
            if callback is not None:
                callback(report)
            if stop_on_convergence and report.converged:
                break
        return self.best

    def state_dict(self) -> dict:
        """Everything ``step`` continues from besides the problem, config and evaluator, as copies: loaded with
        ``load_state`` into a new Estimator of the same problem and config, the next steps equal this one's bit
        for bit. ``rng`` is numpy's ``bit_generator.state`` (plain strings and ints, JSON-serialisable); the
        particle arrays are None before the first step."""
        return {
            "iteration": self.iteration,
            "rng": self.rng.bit_generator.state,
            "hypotheses": None if self.hypotheses is None else self.hypotheses.copy(),
            "projected": None if self.projected is None else self.projected.copy(),
            "loglik": None if self.loglik is None else self.loglik.copy(),
            "status": None if self.status is None else self.status.copy(),
            "history": [replace(r, timings=dict(r.timings)) for r in self.history],
            "best_history": [b.copy() for b in self.best_history],
            "beta": self._beta,
            "calm": self._calm,
        }

    def load_state(self, state: dict) -> None:
        """Continue from a ``state_dict()``. The caller vouches that it belongs to this problem and config
        (``sessions.load_session`` checks a saved one)."""
        self.rng.bit_generator.state = state["rng"]  # raises ValueError for another kind of generator
        self.iteration = int(state["iteration"])
        for name in ("hypotheses", "projected", "loglik", "status"):
            setattr(self, name, None if state[name] is None else np.array(state[name]))
        self.history = [replace(r, timings=dict(r.timings)) for r in state["history"]]
        self.best_history = [np.array(b) for b in state["best_history"]]
        self._beta = float(state["beta"])
        self._calm = int(state["calm"])

    def _propose(self, parents: np.ndarray) -> np.ndarray:
        """Gaussian diffusion, plus the occasional large move (new heading or face, new place)."""
        cfg, models, table = self.config, self.problem.models, self.problem.table
        proposals = diffuse(self.rng, parents, cfg.sigma, cfg.state)
        proposals = random_turns(self.rng, proposals, cfg.turn_prob, cfg.state)
        return random_relocations(self.rng, proposals, cfg.relocate_prob, models, table)

    def _keep_parents(self, idx: np.ndarray) -> None:
        self.hypotheses = self.hypotheses[idx]
        self.projected = self.projected[idx]
        self.loglik = self.loglik[idx]
        self.status = self.status[idx]

    def _adopt(self, hypotheses: np.ndarray, ev: Evaluation, take: np.ndarray) -> None:
        """Replace particles where ``take`` (N,) is true with the evaluated ``hypotheses``."""
        if self.hypotheses is None or len(self.hypotheses) != len(take):
            self.hypotheses, self.projected = hypotheses.copy(), ev.projected.copy()
            self.loglik, self.status = ev.loglik.copy(), ev.status.copy()
            return
        self.hypotheses[take] = hypotheses[take]
        self.projected[take] = ev.projected[take]
        self.loglik[take] = ev.loglik[take]
        self.status[take] = ev.status[take]

    def _report(self, ev: Evaluation, t_resample: float, t_total: float, accept_rate: float) -> IterationReport:
        best = self.best
        if self.best_history:
            prev = self.best_history[-1]
            move_m = float(np.max(np.linalg.norm(best[:, :3, 3] - prev[:, :3, 3], axis=-1)))
            move_deg = float(np.degrees(np.max(symmetric_angle(self.problem, prev, best))))
            calm = move_m < self.config.converge_position and move_deg < self.config.converge_degrees
            self._calm = self._calm + 1 if calm else 0
        else:
            move_m = move_deg = float("nan")
        self.best_history.append(best.copy())
        finite = np.isfinite(self.loglik)
        timings = dict(ev.timings)
        timings["resampling"] = t_resample
        timings["total"] = t_total
        return IterationReport(
            iteration=self.iteration,
            best_loglik=float(self.loglik[self.best_index]),
            mean_loglik=float(self.loglik[finite].mean()) if finite.any() else float("-inf"),
            ess=ess(self._beta * self.loglik),
            beta=self._beta,
            best_move_m=move_m,
            best_move_deg=move_deg,
            converged=self.converged,
            n_failed=int((~finite).sum()),
            accept_rate=accept_rate,
            timings={k: float(timings.get(k, 0.0)) for k in (*STAGES, "resampling", "total")},
        )


def object_confidence(problem: Problem, projected: np.ndarray, weights: np.ndarray, best: np.ndarray,
                      radius: float = 0.02) -> np.ndarray:
    """Per object, the weight share of particles that place it within ``radius`` of the best scene -> (K,) in [0, 1].
    Used as the BOP result score."""
    near = np.linalg.norm(projected[:, :, :3, 3] - best[None, :, :3, 3], axis=-1) < radius  # (N, K)
    return (weights[:, None] * near).sum(axis=0)
