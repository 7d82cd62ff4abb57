"""The estimator a user runs: PI-PF or PI-MCPF (``inference.smc.filter``) with the paper's search or the default one
(``inference.search.paper_search``, ``inference.search.default_search``), its settings, its answer, and its state
for sessions.

``Estimator.run`` steps the filter until the iteration budget or the paper's convergence rule, then returns the
search's answer (``settle``): for the default search the estimate fitted to the depth, with its near ties.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from workbench.evaluation import Evaluator
from workbench.inference.answer.posterior import Posterior
from workbench.inference.answer.settle import Tie
from workbench.inference.clock import ITERATE_SHARE, StageClock
from workbench.inference.config import EstimatorConfig
from workbench.inference.search import datadriven
from workbench.inference.search.default_search import DefaultSearch
from workbench.inference.search.moves.registry import MoveKind
from workbench.inference.search.paper_search import PaperSearch
from workbench.inference.smc.filter import IterationReport, ParticleFilter, Search
from workbench.io import readers as read
from workbench.problem.problem import Problem
from workbench.sessions.answer import Answer, answer_json, parse_answer


def make_search(problem: Problem, proposals: str) -> Search:
    """The search of ``EstimatorConfig.proposals``."""
    return PaperSearch() if proposals == "paper" else DefaultSearch(problem)


class Estimator:
    """A particle filter (``filter``) stepped with a search (``search``), and the run's answer. The particle set is
    ``particles`` (``ParticleSet``, table frame); the estimate (``estimate``) is the best scene ever evaluated, with
    ``estimate_loglik``: it never gets worse from one iteration to the next. ``run`` returns it settled (``settle``)."""

    def __init__(self, problem: Problem, config: EstimatorConfig, evaluator: Evaluator | None,
                 search: Search | None = None):
        """``search``: another search than ``config.proposals``' (a tracked frame's, ``track_search``)."""
        config.validate()
        self.problem = problem
        self.search = make_search(problem, config.proposals) if search is None else search
        self.filter = ParticleFilter(problem, config, evaluator, self.search)
        self.settle_scenes = 0  # scenes settling scored as given (a render each, no physics)
        self.settled: np.ndarray | None = None  # the estimate fitted to the depth (``settle``), once asked for
        self.settled_loglik = float("-inf")  # its log-likelihood as given (no physics)
        self.ties: list[Tie] = []  # the settled estimate's near ties, found with it
        self.posterior: Posterior | None = None  # per object, the modes the view leaves open, found with it
        self._settled_from: np.ndarray | None = None  # the estimate it was settled from

    @property
    def config(self) -> EstimatorConfig:
        return self.filter.config

    @property
    def evaluator(self) -> Evaluator | None:
        return self.filter.evaluator

    @evaluator.setter
    def evaluator(self, evaluator: Evaluator) -> None:
        """A new evaluator, e.g. a fresh pool after a worker died; results do not depend on which one runs."""
        self.filter.evaluator = evaluator

    def set_config(self, config: EstimatorConfig) -> None:
        """Takes effect at the next step; the particle set is kept (its size changes at the next resampling), and
        so is the seed. Another ``proposals`` switches the search (the default one fits its library anew)."""
        config.validate()
        if config.proposals != self.config.proposals:
            self.search = self.filter.search = make_search(self.problem, config.proposals)
        self.filter.config = replace(config, seed=self.config.seed)
        self._settled_from = None  # settle again, with the new region

    # The filter's state, read by the command line, the benchmarks and the workbench.
    particles = property(lambda self: self.filter.particles)
    iteration = property(lambda self: self.filter.iteration)
    history = property(lambda self: self.filter.history)
    best_history = property(lambda self: self.filter.best_history)
    rng = property(lambda self: self.filter.rng)
    sink = property(lambda self: self.filter.sink)
    evaluations = property(lambda self: self.filter.evaluations)  # hypotheses projected and weighed so far
    estimate = property(lambda self: self.filter.estimated_scene,
                        doc="The estimate: the best scene (K, 4, 4) so far, table frame.")
    estimate_loglik = property(lambda self: self.filter.estimate_loglik)
    estimate_kind = property(lambda self: self.filter.estimate_kind)
    converged = property(lambda self: self.filter.converged)

    @property
    def best_index(self) -> int:
        """The most likely particle of the current set."""
        return int(np.argmax(self.particles.loglik))

    def weights(self) -> np.ndarray:
        """(N,) normalised weights of the current particles, with this iteration's tempering."""
        return self.filter.weights()

    def step(self) -> IterationReport:
        return self.filter.step()

    def run(self, iterations: int | None = None, stop_on_convergence: bool = True, callback=None,
            started: float | None = None) -> np.ndarray:
        """Step until ``iterations`` (default: the config's), convergence or the config's ``budget_s`` -> the best
        scene (K, 4, 4), settled. The budget counts from ``started`` (a ``time.perf_counter()``; default now), so
        that a frame's loading counts against it. The run's time by stage is in ``clock`` (``inference.clock``)."""
        total = self.config.iterations if iterations is None else iterations
        self.start_clock(started)
        while self.iteration < total:
            if self.iteration >= 0 and self.out_of_budget():
                break
            report = self.step()
            if callback is not None:
                callback(report)
            if stop_on_convergence and report.converged:
                break
        return self.settle()

    @property
    def clock(self) -> StageClock:
        return self.filter.clock

    @property
    def cut_short(self) -> str | None:
        """The stages of this run the budget skipped, in order, of "iterations", "polish" and "settle", "turns",
        "posterior" (the answer from there on), e.g. "iterations, posterior"; None where it finished."""
        return self.filter.clock.cut_short

    def out_of_budget(self) -> bool:
        """Whether another iteration, as long as the last one, would pass the iterations' share of the clock's
        budget; if so, the iterations are cut short from here (``cut_short``)."""
        clock = self.filter.clock
        if clock.budget_s is None:
            return False
        last = self.history[-1].timings["total"] if self.history else 0.0
        if clock.elapsed() + last < ITERATE_SHARE * clock.budget_s:
            return False
        clock.cut("iterations")
        return True

    def start_clock(self, started: float | None = None, on_stage=None) -> None:
        """A new ``clock`` with the config's budget, counting from ``started`` (a ``time.perf_counter()``; default
        now): a run's time and its cuts are its own. ``on_stage(name)``: told of each stage the run enters."""
        self.filter.clock = StageClock(self.config.budget_s, started, on_stage)

    def settle(self) -> np.ndarray:
        """The search's answer from the estimate (``Search.finish``; the default search fits it to the observed
        depth without physics) -> (K, 4, 4); also kept in ``settled``, with its log-likelihood as given in
        ``settled_loglik``, its near ties in ``ties`` and the posterior per object in ``posterior``. Computed once
        per estimate: stepping on and settling again starts from the new estimate."""
        if self.answer_current:
            return self.settled
        self.filter.weigh_floor_in()  # the answer is judged by the whole likelihood (stopped early or not)
        estimate = self.filter.estimate
        answer = self.search.finish(self.filter)
        self.settled, self.settled_loglik, self.ties = answer.scene, answer.loglik, answer.ties
        self.posterior = answer.posterior
        if self.posterior is not None and self.cut_short is not None:  # the run's cuts, not only its answer's
            self.posterior = replace(self.posterior, cut_short=self.cut_short)
        self.settle_scenes += answer.scored
        self._settled_from = None if estimate is None else estimate.copy()
        return self.settled

    @property
    def answer_current(self) -> bool:
        """Whether ``settled`` (with ``ties`` and ``posterior``) is the answer for the current estimate: settled
        since the estimate last changed, and since the settings last changed."""
        m = self.filter.estimate
        return self._settled_from is not None and m is not None and np.array_equal(self._settled_from, m)

    @property
    def current_posterior(self) -> Posterior | None:
        """The posterior of the current estimate, or None (not settled since it changed, or the paper's search)."""
        return self.posterior if self.answer_current else None

    # ------------------------------------------------------------------------------------------------ sessions
    def state_dict(self) -> dict:
        """Everything ``step`` continues from besides the problem, config and evaluator, as copies: loaded with
        ``load_state`` into a new Estimator of the same problem and config, the next steps equal this one's bit
        for bit. The filter's state (``ParticleFilter.state_dict``), its ``search`` entry with the search's memory
        added (``Search.state_dict``, plain JSON values), and ``answer``: the settled answer of the current
        estimate (``sessions.answer``: scene, log-likelihood, ties, posterior) as plain lists, None when not
        settled, so that a restored estimator shows the same posterior without settling again."""
        state = self.filter.state_dict()
        state["search"].update(self.search.state_dict())
        state["answer"] = (answer_json(Answer(self.settled, self.settled_loglik, self.ties, self.posterior))
                           if self.answer_current else None)
        return state

    def load_state(self, state: dict) -> None:
        """Continue from a ``state_dict()``. The caller vouches that it belongs to this problem and config
        (``sessions.store.load_session`` checks a saved one, ``search`` included)."""
        search = parse_search(state.get("search"), self.problem.n_objects)
        self.filter.load_state(state, search)
        self.search.load_state(search)
        answer = parse_answer(state.get("answer"), self.problem.n_objects)
        estimate = self.filter.estimate
        if answer is not None and estimate is None:
            raise ValueError("answer: a settled answer without an estimate to belong to")
        self.settled = None if answer is None else answer.scene
        self.settled_loglik = float("-inf") if answer is None else answer.loglik
        self.ties = [] if answer is None else list(answer.ties)
        self.posterior = None if answer is None else answer.posterior
        self._settled_from = None if answer is None else estimate.copy()


def parse_search(search, K: int) -> dict:
    """The ``search`` entry of a ``state_dict`` (plain JSON lists) for K objects -> ``map`` (K, 4, 4) or None,
    ``map_loglik``, ``map_kind`` (MoveKind), ``floor_in`` (``ParticleFilter.floor_in``; true in states saved
    before it existed), ``sink`` (m), ``evaluations``, ``library`` (datadriven.Library or None), ``fitted``,
    ``polished_at``, ``offered_for`` and ``offered`` (``DefaultSearch``'s; none fitted, never polished and nothing
    offered in states saved before they existed). None (a state saved before the search existed) gives the
    neutral values. Raises ValueError naming what is malformed."""
    if search is None:
        search = {}
    if not isinstance(search, dict):
        raise ValueError("search must be an object")
    try:
        m = search.get("map")
        ll = search.get("map_loglik")
        sink = float(read.finite_array(search.get("sink", 0.0), (), np.float64, "search.sink"))
        if not 0.0 <= sink <= 1.0:
            raise ValueError(f"search.sink must lie in [0, 1] m, got {sink}")
        lib = search.get("library")
        library = None
        if lib is not None:
            poses = [read.table_poses(p, (len(p), 4, 4), "search.library.poses") if len(p) else np.zeros((0, 4, 4))
                     for p in lib["poses"]]
            weights = [read.finite_array(w, (len(p),), np.float64, "search.library.weights")
                       for w, p in zip(lib["weights"], poses)]
            if len(poses) != K or len(weights) != K:
                raise ValueError(f"search.library must list {K} objects")
            if any(len(w) and (np.any(w < 0) or abs(w.sum() - 1.0) > 1e-6) for w in weights):
                raise ValueError("search.library.weights must be probabilities: >= 0, summing to 1 per object")
            library = datadriven.Library(poses, weights)
        fitted = set()
        for key in search.get("fitted", []):
            pairs = tuple((int(k), tuple(read.finite_array(pose, (16,), np.float64, "search.fitted").tolist()))
                          for k, pose in key)
            if not pairs or any(not 0 <= k < K for k, _ in pairs):
                raise ValueError(f"search.fitted must list assemblies of objects 0 to {K - 1}")
            fitted.add(pairs)
        polished_at = search.get("polished_at")
        offered_for, offered = search.get("offered_for"), search.get("offered", [])
        if offered_for is not None and not isinstance(offered_for, str) \
                or not isinstance(offered, list) or not all(isinstance(d, str) for d in offered):
            raise ValueError("search.offered_for must be text or null, and search.offered a list of texts")
        return {
            "map": None if m is None else read.table_poses(m, (K, 4, 4), "search.map"),
            "map_loglik": float("-inf") if ll is None
            else float(read.finite_array(ll, (), np.float64, "search.map_loglik")),
            "map_kind": MoveKind(int(search.get("map_kind", 0))),
            "floor_in": read.boolean(search.get("floor_in", True), "search.floor_in"),
            "sink": sink,
            "evaluations": int(read.finite_array(search.get("evaluations", 0), (), np.int64, "search.evaluations")),
            "library": library,
            "fitted": fitted,
            "polished_at": float("-inf") if polished_at is None
            else float(read.finite_array(polished_at, (), np.float64, "search.polished_at")),
            "offered_for": offered_for,
            "offered": set(offered),
        }
    except (TypeError, KeyError, IndexError, OverflowError) as e:
        raise ValueError(f"malformed search entry ({type(e).__name__}: {e})") from e


def object_confidence(problem: Problem, projected: np.ndarray, weights: np.ndarray, best: np.ndarray,
                      radius: float = 0.02) -> np.ndarray:
    """Per object, the weight share of particles that place it within ``radius`` of the best scene -> (K,) in [0, 1].
    Used as the BOP result score."""
    near = np.linalg.norm(projected[:, :, :3, 3] - best[None, :, :3, 3], axis=-1) < radius  # (N, K)
    return (weights[:, None] * near).sum(axis=0)
