"""The filter core: PI-PF and PI-MCPF over one ``ParticleSet``, with tempering, the Metropolis-Hastings accept
step, the estimate (MAP) and the paper's convergence rule. Where hypotheses come from is the search's business
(``Search``: its hooks start, propose, after_step and finish), as ``particles``' ``SMC`` leaves it to its
``FeynmanKac`` model: ``paper_search.PaperSearch`` (the paper's) and ``default_search.DefaultSearch``.

The filter is the one owner of its state: a search reads it, and hands what it changes back as an ``Update``
(scenes offered for the estimate, particles to replace the worst, a new sink), which only ``ParticleFilter.apply``
writes. ``after_step`` yields its updates one by one, each applied before the search goes on, so that a later
part of the step (polish after the sink is fitted) sees the state the earlier one left.

One ``step()`` is one iteration:
- PI-PF: resample the projected particles by their tempered likelihood, move them (the search's proposals),
  evaluate (project to rest, render, weigh).
- PI-MCPF: resample, then one Metropolis-Hastings move per particle: the search proposes X* with its log-q
  correction, X* is projected and weighed, accepted with probability min(1, L(X*)/L(X) q-ratio) (in log space,
  with the same tempering as the weights).
Both evaluate N hypotheses per iteration, so their costs compare one to one. Iteration 0 is the search's start.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field, replace
from typing import Protocol

import numpy as np

from workbench.evaluation import STAGES, Done, Evaluation, Evaluator, Pending
from workbench.geometry import rotation_angle
from workbench.inference.answer.posterior import Posterior
from workbench.inference.answer.settle import Tie
from workbench.inference.clock import StageClock
from workbench.inference.config import EstimatorConfig
from workbench.inference.search.moves.registry import MoveKind
from workbench.inference.smc.particleset import ParticleSet
from workbench.inference.smc.resampling import (
    ess,
    normalised_weights,
    systematic_resample,
    temper_to_ess,
)
from workbench.problem.problem import Problem


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
    n_failed: int  # particles whose physics blew up or left the table, or that rest outside the object region
    accept_rate: float  # PI-MCPF only (nan for PI-PF)
    timings: dict[str, float]
    # Per move kind: how many were proposed this iteration, and how many were accepted (PI-MCPF) or, for PI-PF,
    # the expected number of their offspring at the next resampling (N times their share of the weight).
    moves: dict[str, dict[str, float]] = field(default_factory=dict)
    best_kind: str = ""  # the move kind that produced the estimate (the best scene evaluated so far)
    sink_m: float = 0.0  # how far below the fitted table plane the objects rest (see ParticleFilter)

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class Proposed:
    """What a search's ``propose`` returns for N resampled parents: ``hypotheses`` (N, K, 4, 4), ``log_q`` (N,)
    Metropolis-Hastings corrections, ``kinds`` (N,) int8 MoveKind, their ``evaluation``, and ``waited`` seconds
    spent waiting for the workers (not the main process's own work)."""

    hypotheses: np.ndarray
    log_q: np.ndarray
    kinds: np.ndarray
    evaluation: Evaluation
    waited: float


@dataclass
class Settled:
    """What a run returns: the ``scene`` (K, 4, 4) table frame, its log-likelihood as given (no physics), the
    near ties left (``settle.Tie``), how many scenes finishing scored (a render each, no physics), and the
    posterior per object (``posterior.Posterior``) where the search computes one."""

    scene: np.ndarray
    loglik: float
    ties: list[Tie] = field(default_factory=list)
    scored: int = 0
    posterior: Posterior | None = None


@dataclass
class Update:
    """What a search changes in the filter's state, applied by ``ParticleFilter.apply`` in this order: the ``sink``
    (m) for every later evaluation; an ``estimate`` (scene (K, 4, 4), its log-likelihood) that replaces the
    estimate, keeping the kind that made it (the same scene at a better sink); ``offered`` scenes (an
    ``Evaluation`` and their (B,) MoveKind) that compete for the estimate; ``replacements``, particles that take
    the places of the least likely ones."""

    sink: float | None = None
    estimate: tuple[np.ndarray, float] | None = None
    offered: tuple[Evaluation, np.ndarray] | None = None
    replacements: ParticleSet | None = None


@dataclass
class Started:
    """What a search's ``start`` returns: the (N, K, 4, 4) initial ``hypotheses``, their (N,) int8 MoveKind
    ``kinds``, and an ``update`` applied before they are evaluated (a tracked frame's sink). ``project``: False
    when the hypotheses are at rest already (a tracked frame's carried particles), scored as given."""

    hypotheses: np.ndarray
    kinds: np.ndarray
    update: Update = field(default_factory=Update)
    project: bool = True


@dataclass
class _WithoutFloor:
    """A pending evaluation whose log-likelihoods leave out the clutter floor's part (before
    ``ParticleFilter.floor_at``)."""

    pending: Pending

    def result(self) -> Evaluation:
        ev = self.pending.result()
        return replace(ev, loglik=ev.loglik - ev.floor_gain, floor_gain=np.zeros_like(ev.floor_gain))


@dataclass
class _Clocked:
    """A pending evaluation whose wait, hypotheses and worker seconds go to the clock's stage that asks for it."""

    pending: Pending
    clock: StageClock
    n: int
    project: bool

    def result(self) -> Evaluation:
        with self.clock.waiting():
            ev = self.pending.result()
        self.clock.count(self.n, self.project, ev.timings)
        return ev


class Search(Protocol):
    """The hooks the filter calls. A search reads the filter's state and never writes it: what it changes comes
    back as ``Started``/``Update`` for the filter to apply. Its own memory between steps (candidates, scenes
    already fitted) is saved with sessions through ``state_dict``/``load_state``."""

    def start(self, filt: "ParticleFilter") -> Started:
        """Iteration 0: the initial hypotheses and their kinds."""
        ...

    def propose(self, filt: "ParticleFilter", parents: np.ndarray) -> Proposed:
        """One move per resampled parent (N, K, 4, 4), evaluated (``filt.submit``)."""
        ...

    def after_step(self, filt: "ParticleFilter") -> Iterable[Update]:
        """After an iteration's particles and estimate are updated (``filt.iteration`` not yet incremented): the
        updates, each applied before the next is made."""
        ...

    def finish(self, filt: "ParticleFilter") -> Settled:
        """The run's answer from the estimate ``filt.estimate``."""
        ...

    def state_dict(self) -> dict:
        """The search's memory between steps as plain JSON values (the ``search`` entry of a session)."""
        ...

    def load_state(self, search: dict) -> None:
        """Continue from a parsed ``search`` entry (``estimator.parse_search``)."""
        ...


def symmetric_angle(problem: Problem, A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Per object, the rotation angle (rad) between scenes A and B (K, 4, 4), up to each model's symmetries -> (K,)."""
    out = np.empty(len(problem.models))
    for k, model in enumerate(problem.models):
        rel = A[k, :3, :3].T @ B[k, :3, :3]  # (3, 3)
        out[k] = rotation_angle(rel[None] @ model.symmetries[:, :3, :3]).min()
    return out


class ParticleFilter:
    """Holds the particle set (``particles``, table frame) and steps it with ``search``'s proposals. The estimate
    (``estimate``, with ``estimate_loglik`` and the ``estimate_kind`` that produced it) is the best scene ever
    evaluated, accepted or not: it never gets worse from one iteration to the next.

    ``sink`` (m): how far below the fitted table plane (z = 0) the objects rest in physics, for every hypothesis
    evaluated. On real frames the objects' depth puts them several millimetres *into* the plane fitted to the
    table's depth around them; the default search fits the sink as one unknown of the scene, the paper's keeps 0.
    ``evaluations`` counts the hypotheses projected and weighed; ``clock`` says where the run's wall time went, and
    holds its budget (``inference.clock``: made anew by ``Estimator.run``; not part of the state)."""

    def __init__(self, problem: Problem, config: EstimatorConfig, evaluator: Evaluator | None, search: Search):
        self.problem = problem
        self.config = config
        self.evaluator = evaluator
        self.search = search
        self.rng = np.random.default_rng(config.seed)
        self.iteration = -1
        self.particles: ParticleSet | None = None
        self.history: list[IterationReport] = []
        self.best_history: list[np.ndarray] = []
        self.beta = 1.0
        self.calm = 0
        self.estimate: np.ndarray | None = None
        self.estimate_loglik = float("-inf")
        self.estimate_kind = MoveKind.START
        self.sink = 0.0
        self.evaluations = 0
        self.floor_in = self.floor_at <= 0
        self.clock = StageClock()

    @property
    def floor_at(self) -> int:
        """How many steps (the start counts) weigh hypotheses without the clutter floor's part of the
        log-likelihood (``EstimatorConfig.floor_from``); 0 where the likelihood has no floor."""
        if not self.problem.config.likelihood.floored:
            return 0
        return int(np.ceil(self.config.floor_from * self.config.iterations))

    def weigh_floor_in(self) -> None:
        """From now on the clutter floor's part of the log-likelihood counts: the particles and the estimate are
        scored again as they rest (no physics; the best particle may become the estimate), and the convergence
        count starts again. Nothing to do when it counts already."""
        if self.floor_in:
            return
        self.floor_in = True
        self.calm = 0
        with self.clock.stage("floor"):
            self._weigh_again()

    def _weigh_again(self) -> None:
        """The estimate and the particles scored again as they rest, with the clutter floor in."""
        if self.estimate is not None:
            self.estimate_loglik = float(self.evaluate(self.estimate[None], project=False).loglik[0])
        if self.particles is not None and np.isfinite(self.particles.loglik).any():
            ok = np.nonzero(np.isfinite(self.particles.loglik))[0]
            ev = self.evaluate(self.particles.projected[ok], project=False)
            self.particles.loglik[ok] = ev.loglik
            self._offer(ev, self.particles.kinds[ok])
            self.beta = temper_to_ess(self.particles.loglik, self.config.target_ess)

    @property
    def estimated_scene(self) -> np.ndarray:
        """The estimate (K, 4, 4); before any scene was evaluated successfully, the current set's best."""
        if self.estimate is not None:
            return self.estimate
        return self.particles.projected[int(np.argmax(self.particles.loglik))]

    @property
    def converged(self) -> bool:
        return self.calm >= self.config.converge_patience and self.floor_in

    def weights(self) -> np.ndarray:
        """(N,) normalised weights of the current particles, with this iteration's tempering."""
        return normalised_weights(self.beta * self.particles.loglik)

    # ---------------------------------------------------------------------------------------------- evaluation
    def submit(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Pending:
        """Hand (B, K, 4, 4) hypotheses to the evaluator at the scene's sink (or ``sink`` (B,) m); see
        ``Evaluator.submit``."""
        if len(hypotheses) == 0:  # nothing to send the workers
            n, K = 0, self.problem.n_objects
            return Done(Evaluation(np.zeros((n, K, 4, 4)), np.zeros(n), np.zeros(n, np.int8), np.zeros(n)))
        if project:
            self.evaluations += len(hypotheses)
        sink = np.full(len(hypotheses), self.sink) if sink is None else sink
        pending = _Clocked(self.evaluator.submit(hypotheses, sink, project), self.clock, len(hypotheses), project)
        return pending if self.floor_in else _WithoutFloor(pending)

    def evaluate(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Evaluation:
        return self.submit(hypotheses, sink, project).result()

    def _offer(self, ev: Evaluation, kinds: np.ndarray) -> None:
        """Every evaluated scene, accepted or not, competes for the estimate."""
        i = int(np.argmax(ev.loglik))
        if ev.loglik[i] > self.estimate_loglik:
            self.estimate, self.estimate_loglik = ev.projected[i].copy(), float(ev.loglik[i])
            self.estimate_kind = MoveKind(int(kinds[i]))

    def apply(self, update: Update) -> None:
        """A search's changes (``Update``, in its order). The replacements take the least likely particles' places
        (at most as many as there are particles)."""
        if update.sink is not None:
            self.sink = update.sink
        if update.estimate is not None:
            scene, loglik = update.estimate
            self.estimate, self.estimate_loglik = scene, loglik
        if update.offered is not None:
            self._offer(*update.offered)
        if update.replacements is not None:
            worst = np.argsort(self.particles.loglik, kind="stable")[: len(update.replacements)]
            self.particles.put(worst, update.replacements)

    # ------------------------------------------------------------------------------------------------ sessions
    def state_dict(self) -> dict:
        """Everything ``step`` continues from besides the problem, config, evaluator and the search's own memory,
        as copies. ``rng`` is numpy's ``bit_generator.state`` (plain strings and ints); ``particles`` the
        ``ParticleSet``, None before the first step; ``search`` the estimate, the sink and the counts as plain
        JSON values (the search adds its memory to this entry; the keys are the session format's)."""
        return {
            "iteration": self.iteration,
            "rng": self.rng.bit_generator.state,
            "particles": None if self.particles is None else self.particles.copy(),
            "history": [replace(r, timings=dict(r.timings), moves={k: dict(v) for k, v in r.moves.items()})
                        for r in self.history],
            "best_history": [b.copy() for b in self.best_history],
            "beta": self.beta,
            "calm": self.calm,
            "search": {
                "map": None if self.estimate is None else self.estimate.tolist(),
                "map_loglik": self.estimate_loglik if np.isfinite(self.estimate_loglik) else None,
                "map_kind": int(self.estimate_kind),
                "floor_in": self.floor_in,
                "sink": self.sink,
                "evaluations": self.evaluations,
            },
        }

    def load_state(self, state: dict, search: dict) -> None:
        """Continue from a ``state_dict()`` whose ``search`` entry was parsed (``estimator.parse_search``)."""
        self.rng.bit_generator.state = state["rng"]  # raises ValueError for another kind of generator
        self.iteration = int(state["iteration"])
        self.particles = None if state["particles"] is None else state["particles"].copy()
        self.history = [replace(r, timings=dict(r.timings)) for r in state["history"]]
        self.best_history = [np.array(b) for b in state["best_history"]]
        self.beta = float(state["beta"])
        self.calm = int(state["calm"])
        self.estimate, self.estimate_loglik = search["map"], search["map_loglik"]
        self.estimate_kind = search["map_kind"]
        self.floor_in = search["floor_in"]
        self.sink, self.evaluations = search["sink"], search["evaluations"]

    # --------------------------------------------------------------------------------------------------- steps
    def step(self) -> IterationReport:
        with self.clock.stage("filter"):  # what the search's own stages inside it leave over
            return self._step()

    def _step(self) -> IterationReport:
        cfg = self.config
        t0 = time.perf_counter()
        accept_rate, accepted = float("nan"), None
        if self.iteration + 1 >= self.floor_at or (cfg.floor_calm is not None and self.calm >= cfg.floor_calm):
            self.weigh_floor_in()
        if self.iteration < 0:
            with self.clock.stage("start"):
                started = self.search.start(self)
                self.apply(started.update)
                start, kinds = started.hypotheses, started.kinds
                t_resample = time.perf_counter() - t0
                ev = self.evaluate(start, project=started.project)
            self.particles = ParticleSet.evaluated(start, ev, kinds)
        else:
            idx = systematic_resample(self.beta * self.particles.loglik, self.rng, cfg.particles)
            parents = self.particles[idx]
            with self.clock.stage("proposals"):
                p = self.search.propose(self, parents.projected)
            t_resample = time.perf_counter() - t0 - p.waited  # the main process's own work
            ev, kinds = p.evaluation, p.kinds
            proposed = ParticleSet.evaluated(p.hypotheses, ev, kinds)
            if cfg.method == "pipf":
                self.particles = proposed
            else:
                log_ratio = self.beta * (ev.loglik - parents.loglik) + p.log_q
                with np.errstate(invalid="ignore"):
                    accepted = np.log(self.rng.random(len(idx))) < np.nan_to_num(log_ratio, nan=-np.inf)
                accept_rate = float(accepted.mean())
                parents.copyto(proposed, accepted)
                self.particles = parents
        self._offer(ev, kinds)
        for update in self.search.after_step(self):
            self.apply(update)
        self.iteration += 1
        self.beta = temper_to_ess(self.particles.loglik, cfg.target_ess)
        moves = self._move_counts(kinds, accepted)
        report = self._report(ev, t_resample, time.perf_counter() - t0, accept_rate, moves)
        self.history.append(report)
        return report

    def _move_counts(self, kinds: np.ndarray, accepted: np.ndarray | None) -> dict[str, dict[str, float]]:
        """Per move kind of this iteration's proposals: proposed, and accepted (PI-MCPF) or expected offspring at
        the next resampling (PI-PF: N times the tempered weight of that kind's particles)."""
        out = {}
        w = self.weights()
        for kind in np.unique(kinds):
            sel = kinds == kind
            kept = float(accepted[sel].sum()) if accepted is not None else float(len(kinds) * w[sel].sum())
            out[MoveKind(int(kind)).label] = {"proposed": float(sel.sum()), "accepted": kept}
        return out

    def _report(self, ev: Evaluation, t_resample: float, t_total: float, accept_rate: float,
                moves: dict) -> IterationReport:
        best, loglik = self.estimated_scene, self.particles.loglik
        if self.best_history:
            prev = self.best_history[-1]
            move_m = float(np.max(np.linalg.norm(best[:, :3, 3] - prev[:, :3, 3], axis=-1)))
            move_deg = float(np.degrees(np.max(symmetric_angle(self.problem, prev, best))))
            calm = move_m < self.config.converge_position and move_deg < self.config.converge_degrees
            self.calm = self.calm + 1 if calm else 0
        else:
            move_m = move_deg = float("nan")
        self.best_history.append(best.copy())
        finite = np.isfinite(loglik)
        timings = dict(ev.timings)
        timings["resampling"] = t_resample
        timings["total"] = t_total
        return IterationReport(
            iteration=self.iteration,
            best_loglik=self.estimate_loglik,
            mean_loglik=float(loglik[finite].mean()) if finite.any() else float("-inf"),
            ess=ess(self.beta * loglik),
            beta=self.beta,
            best_move_m=move_m,
            best_move_deg=move_deg,
            converged=self.converged,
            n_failed=int((~finite).sum()),
            accept_rate=accept_rate,
            timings={k: float(timings.get(k, 0.0)) for k in (*STAGES, "resampling", "total")},
            moves=moves,
            best_kind=self.estimate_kind.label,
            sink_m=self.sink,
        )
