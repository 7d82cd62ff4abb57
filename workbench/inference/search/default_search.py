"""The default search (``--proposals default``): where its hypotheses come from, around the filter core.

- ``start``: random scenes, most objects taken from the data-driven candidate library, plus whole scenes
  assembled from the candidates.
- ``propose``: one move per particle drawn from the registered kinds (``moves.MoveMix``); the kinds that are cheap
  to make go to the workers first, the library is refitted when due, then the data-driven and ICP moves are made
  while the workers project the others.
- ``after_step``: every ``library_every`` iterations the sink is fitted and the estimate polished (one- and
  two-object variants, stacks, assemblies), each handed to the filter as an ``Update``.
- ``finish``: the estimate settled on the depth without physics, with its half and quarter turns tried and its near
  ties named (``settle``).
Every hypothesis still goes through physics and the likelihood; only where hypotheses come from differs from
the paper.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from functools import partial

import numpy as np

from workbench.evaluation import Evaluation, run_here
from workbench.inference.answer import assemble, polish, posterior, settle
from workbench.inference.clock import ITERATE_SHARE
from workbench.inference.search import datadriven, hiding, leaning
from workbench.inference.search.geometry import SearchGeometry
from workbench.inference.search.moves import gaussian
from workbench.inference.search.moves.context import MoveContext
from workbench.inference.search.moves.registry import REGISTRY, MoveKind
from workbench.inference.search.scenepoints import clusters, object_badness, unexplained
from workbench.inference.smc.filter import (
    ParticleFilter,
    Proposed,
    Settled,
    Started,
    Update,
)
from workbench.inference.smc.particles import initial_particles
from workbench.inference.smc.particleset import ParticleSet
from workbench.meshes.cache import checksum
from workbench.problem.problem import Problem
from workbench.render.depth import DepthRenderer

# The sink (see ParticleFilter) is chosen from 0 to 2 cm in steps of 2 mm: on real frames the objects rest several
# millimetres below the plane fitted to the table's depth (docs/journal/2026-11.md, "The search, third step").
SINK_GRID = np.arange(0.0, 0.0201, 0.002)  # m
# Only while the estimate is stuck (gained less than STUCK since the last polish) does polish assemble with the wide
# beam and try leaning starts. The assemblies that lose to the estimate by less than FIT_WITHIN are fitted to the depth
# (``fit_near_misses``), the best FIT_ASSEMBLIES of them, coarsely (steps down to FIT_MIN_STEP, at most
# FIT_ROUNDS rounds). Fitting recovers a few centimetres of misfit per object, worth hundreds of log-units; an
# assembly losing by thousands is another arrangement, not a misfit, and fitting it costs time and wins nothing
# (docs/journal/2026-11.md, "Gated assembly fits landed").
STUCK = 100.0  # log-units (the estimate creeps up by tens while it is refined; a misplaced object costs hundreds)
FIT_WITHIN = 1000.0  # log-units
FIT_ASSEMBLIES = 2
# And the best FIT_MOVES of polish's one-object moves to another place (a candidate put in place of the object's
# pose): a candidate was fitted alone to its cluster, so where the data shows the object only in part it is a
# centimetre or two off and loses to the estimate at rest until it is fitted in the scene (docs/journal/2026-11.md,
# "Slid fits, fitted one-object moves").
FIT_MOVES = 4
FIT_MIN_STEP = 0.002  # m
FIT_ROUNDS = 10


def fit_sink(filt: ParticleFilter) -> Update:
    """The sink that maximises the estimate's likelihood: the estimate, lowered to each value of SINK_GRID,
    projected and weighed there -> that sink with the estimate at it, only if it beats the estimate as it stands,
    so the estimate never gets worse (else no change). The particles keep the log-likelihoods they had under the
    old sink until their next move."""
    if filt.estimate is None:  # every particle failed physics so far
        return Update()
    with filt.clock.stage("sink"):
        return _fit_sink(filt)


def _fit_sink(filt: ParticleFilter) -> Update:
    scenes = np.repeat(filt.estimate[None], len(SINK_GRID), axis=0)
    scenes[:, :, 2, 3] -= (SINK_GRID - filt.sink)[:, None]
    ev = filt.evaluate(scenes, SINK_GRID)
    i = int(np.argmax(ev.loglik))
    if ev.loglik[i] > filt.estimate_loglik:
        return Update(sink=float(SINK_GRID[i]), estimate=(ev.projected[i].copy(), float(ev.loglik[i])))
    return Update()


def fit_near_misses(filt: ParticleFilter, pools: list[tuple[np.ndarray, np.ndarray, int, int]], estimate: np.ndarray,
                    done: set) -> list[np.ndarray]:
    """Per pool (evaluated scenes (S, K, 4, 4), their log-likelihoods (S,), ``least``, ``most``): the best ``most``
    of its scenes that lost to the estimate (K, 4, 4) by less than FIT_WITHIN, move ``least`` or more of its
    objects to other places (more than ``datadriven.PLACE_M`` away) and were not fitted before (their keys in
    ``done``, which gets theirs), each fitted to
    the depth without physics (``settle.search``, coarsely) in the objects it moves, all pools' in lockstep ->
    per pool (F, K, 4, 4). A scene that keeps the estimate's places is the same arrangement, which settling fits
    anyway.
    Each candidate was fitted alone to its cluster, so one partly hidden by another is often a few centimetres
    off, and the right arrangement then loses to the estimate after physics: generated clutter frame 5 (four
    objects moved together) scored 191 below it as assembled and 21 above it fitted."""
    with filt.clock.stage("near misses"):
        return _fit_near_misses(filt, pools, estimate, done)


def _fit_near_misses(filt: ParticleFilter, pools: list[tuple[np.ndarray, np.ndarray, int, int]],
                     estimate: np.ndarray, done: set) -> list[np.ndarray]:
    cfg, searches, counts = filt.config, [], []
    for scenes, loglik, least, most in pools:
        chosen = 0
        for i in np.argsort(-loglik, kind="stable"):
            if chosen == most:
                break
            moved = assemble.moved(scenes[i], estimate)
            far = datadriven.elsewhere(scenes[i, moved], estimate[moved])
            key = tuple((k, tuple(np.round(scenes[i, k], 6).ravel().tolist())) for k in moved)
            if not filt.estimate_loglik - FIT_WITHIN < loglik[i] <= filt.estimate_loglik or far.sum() < least \
                    or key in done:
                continue
            done.add(key)
            searches.append(settle.search(scenes[i], min_step_m=FIT_MIN_STEP, max_rounds=FIT_ROUNDS,
                                          max_shift_m=cfg.settle_shift, max_turn_deg=cfg.settle_turn,
                                          objects=moved))
            chosen += 1
        counts.append(chosen)
    found = settle.run(searches, lambda scenes: filt.evaluate(scenes, project=False).loglik)
    fitted = np.array([scene for scene, _, _ in found]).reshape(-1, *estimate.shape)
    return np.split(fitted, np.cumsum(counts)[:-1])


class DefaultSearch:
    """The data-driven search's state: the candidate ``library``, the assemblies and one-object moves already
    ``fitted`` (``fit_near_misses``: per scene, the (object, pose) pairs it moves, each pose its 16 entries rounded to
    1e-6) and the estimate's log-likelihood at the last polish (``polished_at``), all saved with sessions; the
    latest refit's candidates alone (``unexplained``: fitted where the estimate leaves points unexplained; polish
    tries them first; made and used within one step, so not saved), and caches: the per-object geometry, the
    leaning starts (``leaning_starts``), the candidates of each cluster already fitted, the bases found under each
    top, which candidates sit inside one another."""

    def __init__(self, problem: Problem):
        self.problem = problem
        self.library: datadriven.Library | None = None
        self.unexplained: datadriven.Library | None = None
        self._geometry: SearchGeometry | None = None
        self._leaning: datadriven.Library | None = None
        self._cluster_memo: dict = {}  # candidates per cluster already fitted (datadriven.build_library)
        self._base_memo: dict = {}  # polish.stacked's bases found under each top so far
        self._clashes: assemble.Clashes | None = None  # which candidates sit inside one another, tested so far
        self.fitted: set[tuple[tuple[int, tuple[float, ...]], ...]] = set()
        self.polished_at = -np.inf
        # What polish offered for the estimate as it stands (``offered_for``: ``polish_key``): the checksums of the
        # scenes (``meshes.cache.checksum``), and of the library its assemblies were made from. An estimate that has
        # not changed since the last polish loses to them again; offered once, they are not evaluated again.
        self.offered_for: str | None = None
        self.offered: set[str] = set()
        self._map_wait = 0.0  # seconds this iteration's proposals waited for fits on the workers

    def geometry(self, filt: ParticleFilter) -> SearchGeometry:
        """Per-object geometry and the observed points, computed at the first use."""
        if self._geometry is None:
            self._geometry = SearchGeometry.of(self.problem, upright=filt.config.state == "xyzyaw")
        return self._geometry

    # ------------------------------------------------------------------------------------------------ hooks
    def start(self, filt: ParticleFilter) -> Started:
        """Random scenes over the object region, most objects taken from the data-driven candidates instead (some
        stay uniform, so that nothing is ruled out), and the assemblies first."""
        cfg = filt.config
        start = initial_particles(filt.rng, cfg.particles, self.problem.models, self.problem.table, cfg.state)
        kinds = np.full(cfg.particles, int(MoveKind.START), np.int8)
        self.refit_library(filt)
        take = filt.rng.random((cfg.particles, self.problem.n_objects)) < cfg.data_start
        start = datadriven.sequential_start(filt.rng, self.library, cfg.particles, self.geometry(filt).radius, take,
                                            start)
        kinds[take.any(axis=1)] = int(MoveKind.DATA_START)
        joint = self._assemblies(filt, start[0])[: cfg.particles]
        start[: len(joint)] = joint
        kinds[: len(joint)] = int(MoveKind.ASSEMBLE)
        return Started(start, kinds)

    def propose(self, filt: ParticleFilter, parents: np.ndarray) -> Proposed:
        """The moves that are cheap to make go to the evaluator first; this process then refits the library (when
        due) and makes the moves that need it (``Move.after_refit``) while the workers project the first ones."""
        cfg, n, geometry = filt.config, len(parents), self.geometry(filt)
        self._map_wait = 0.0
        # Objects that explain their part of the observation worst are moved most often; every object sometimes.
        choose = object_badness(self.problem, filt.estimated_scene, geometry.samples) + 0.1
        scales = gaussian.object_scales(filt.particles.projected, filt.weights(), cfg.sigma, cfg.sigma_floor)
        kinds = cfg.moves.for_state(cfg.state).draw(filt.rng, n)
        out, log_q = parents.copy(), np.zeros(n)
        first = ~np.isin(kinds, [code for code, move in REGISTRY.items() if move.after_refit])
        context = partial(MoveContext, self.problem, geometry, sigma=cfg.sigma, state=cfg.state, method=cfg.method,
                          choose=choose, scales=scales)
        self._propose(filt.rng, parents, kinds, first, out, log_q, context(self.library))
        pending = filt.submit(out[first])
        # A session saved without the search state (or by an older version) has no library yet: fit one now.
        if self.library is None or filt.iteration % cfg.library_every == 0:
            self.refit_library(filt)
        self._propose(filt.rng, parents, kinds, ~first, out, log_q, context(self.library))
        t0 = time.perf_counter()
        ev = Evaluation.interleave(first, pending.result(), filt.evaluate(out[~first]))
        return Proposed(out, log_q, kinds, ev, time.perf_counter() - t0 + self._map_wait)

    def after_step(self, filt: ParticleFilter) -> Iterator[Update]:
        """Every ``library_every`` iterations, the sink fitted and the estimate polished; not once the iterations'
        share of a budget is spent (``clock.ITERATE_SHARE``): the answer needs the rest."""
        if filt.iteration % filt.config.library_every == 0:
            if filt.clock.over(ITERATE_SHARE):
                filt.clock.cut("polish")
                return
            yield fit_sink(filt)
            yield self.polish(filt)

    def finish(self, filt: ParticleFilter) -> Settled:
        """The estimate fitted to the observed depth without physics (``settle.pattern_search``), each object
        within ``settle_shift`` and ``settle_turn`` of its pose in the estimate, then each object's half and quarter
        turns (``settle.turn_over``), each object not turned restarted a few degrees away in the same region
        (``settle.hop``), and the posterior of what it settled on (``posterior.sweep``). The estimate itself, with no
        posterior, when settling is off."""
        cfg, clock = filt.config, filt.clock
        if filt.estimate is None or cfg.settle_shift == 0 or cfg.settle_turn == 0:
            return Settled(filt.estimated_scene.copy(), filt.estimate_loglik)
        if filt.particles is None:  # settled before any step (a label fitted, a test): no particles to spread
            projected, weights = np.zeros((0, *filt.estimate.shape)), np.zeros(0)
        else:
            projected, weights = filt.particles.projected, filt.weights()
        score = lambda scenes: filt.evaluate(scenes, project=False).loglik  # noqa: E731
        rest = lambda scenes: filt.evaluate(scenes).projected  # noqa: E731

        # Each stage only while the budget lasts; where it runs out, the answer is the scene settled so far with the
        # particles' posterior of it (``posterior.unswept``).
        def cut(stage: str, scene: np.ndarray, loglik: float, scored: int) -> Settled:
            clock.cut(stage)
            return Settled(scene, loglik, [], scored,
                           posterior.unswept(self.problem, scene, loglik, projected, weights, stage))

        if clock.over():
            return cut("settle", filt.estimate, filt.estimate_loglik, 0)
        with clock.stage("settle"):
            scene, loglik, scored = settle.pattern_search(
                filt.estimate, score, step_m=settle.SETTLE_STEP, step_deg=settle.SETTLE_DEGREES,
                max_shift_m=cfg.settle_shift, max_turn_deg=cfg.settle_turn)
        if clock.over():
            return cut("turns", scene, loglik, scored)
        with clock.stage("turns"):
            before = scene
            # A turn that could be neither the answer nor a mode stops early, as the posterior's candidates do.
            scene, loglik, turned, ties, turns = settle.turn_over(
                self.problem, scene, loglik, score, rest, cfg.settle_shift, cfg.settle_turn,
                give_up_below=posterior.unreported_below(loglik))
            # After the turns, not before: a restart that leans a mug facing the wrong way can win, and its half
            # turn then no longer does. A turned object was settled from a fresh start; the others restart where
            # physics put them.
            kept = [k for k in range(len(scene)) if np.array_equal(scene[k], before[k])]
            scene, loglik, hopped = settle.hop(self.problem, scene, loglik, score, rest, filt.estimate,
                                               cfg.settle_shift, cfg.settle_turn, kept)
            scored += turned + hopped
        if clock.over():
            return cut("posterior", scene, loglik, scored)
        with clock.stage("posterior"):
            scorer = settle.Scorer(score, rest, cfg.settle_shift, cfg.settle_turn, partial(self._run, filt))
            found, swept, final, loglik = posterior.sweep(
                self.problem, posterior.SweepStart(scene, loglik, turns, before, projected, weights), scorer,
                self.geometry(filt))
        ties = [t for t in ties if np.array_equal(final[t.obj], scene[t.obj])]  # an object the sweep moved: its own
        return Settled(final, loglik, ties, scored + swept, found)

    # ------------------------------------------------------------------------------------------------ sessions
    def state_dict(self) -> dict:
        """What the search remembers between steps, as plain JSON values: the candidate ``library`` (None before
        the first fit), the scenes already ``fitted`` (each a list of [object, 16 pose entries]), ``polished_at``
        (None before the first polish) and what polish ``offered`` for the estimate (``offered_for``). The caches
        are made again on use."""
        lib = self.library
        return {
            "library": None if lib is None else {"poses": [p.tolist() for p in lib.poses],
                                                 "weights": [w.tolist() for w in lib.weights]},
            "fitted": [[[k, list(pose)] for k, pose in key] for key in sorted(self.fitted)],
            "polished_at": float(self.polished_at) if np.isfinite(self.polished_at) else None,
            "offered_for": self.offered_for,
            "offered": sorted(self.offered),
        }

    def load_state(self, search: dict) -> None:
        """Continue from a parsed ``search`` entry (``estimator.parse_search``)."""
        self.library = search["library"]
        self.fitted, self.polished_at = search["fitted"], search["polished_at"]
        self.offered_for, self.offered = search["offered_for"], search["offered"]

    # -------------------------------------------------------------------------------------------------- parts
    @staticmethod
    def _propose(rng: np.random.Generator, parents: np.ndarray, kinds: np.ndarray, which: np.ndarray,
                 out: np.ndarray, log_q: np.ndarray, ctx: MoveContext) -> None:
        """Fill ``out`` (N, K, 4, 4) and ``log_q`` (N,) where ``which`` (N,) is true: the move of kind ``kinds``
        (N,) from ``parents`` (N, K, 4, 4), kind by kind in code order (the order of the random draws)."""
        for kind in np.unique(kinds[which]):
            sel = np.nonzero(which & (kinds == kind))[0]
            p = REGISTRY[int(kind)].propose(rng, parents[sel], ctx)
            out[sel], log_q[sel] = p.hypotheses, p.log_q_ratio

    def _run(self, filt: ParticleFilter, fn, calls: list[tuple]) -> list:
        """``Evaluator.map``: the candidate fits run on the evaluator's workers, which would otherwise wait for this
        process (here when there is no evaluator). The wait is counted in ``_map_wait``, not as this process's
        own work."""
        if filt.evaluator is None:
            return run_here(self.problem)(fn, calls)
        t0 = time.perf_counter()
        try:
            with filt.clock.waiting():
                return filt.evaluator.map(fn, calls)
        finally:
            self._map_wait += time.perf_counter() - t0

    def refit_library(self, filt: ParticleFilter, scene: np.ndarray | None = None) -> None:
        """Candidates from the clusters of observed points the estimate (or ``scene`` (K, 4, 4), when given) does
        not explain (all of them before the first estimate), merged with the earlier candidates. A refit leaves out
        clusters under ``REFIT_MIN_POINTS`` and the rims of the estimate (``datadriven.rims``)."""
        with filt.clock.stage("library"):
            self._refit_library(filt, scene)

    def _refit_library(self, filt: ParticleFilter, scene: np.ndarray | None) -> None:
        g = self.geometry(filt)
        scene = filt.estimate if scene is None else scene
        loose = unexplained(self.problem, g.points, scene, g.samples)
        groups = clusters(g.points.points[loose])
        if self.library is not None:  # a refit: what the estimate leaves, less the small clusters and its rims
            groups = [c for c in groups if len(c) >= datadriven.REFIT_MIN_POINTS]
            if scene is not None:
                groups = [c for c, rim in zip(groups, datadriven.rims(groups, scene, g.samples)) if not rim]
        fresh = datadriven.build_library(self.problem, groups, g, self._cluster_memo, partial(self._run, filt))
        self.library = fresh if self.library is None else self.library.merged(fresh)
        self.unexplained = fresh

    def leaning_starts(self, filt: ParticleFilter) -> datadriven.Library | None:
        """``leaning.library`` of the clusters of all observed points, made at the first use (None when
        ``EstimatorConfig.leaning`` is off). Of all points, not of those the estimate leaves unexplained: an object
        the estimate puts over part of a leaning box leaves too little of its slanted side to make a patch (real-
        shape frame 17: 116 points of the gelatin box's side left, none of them a patch)."""
        if not filt.config.leaning:
            return None
        if self._leaning is None:
            g = self.geometry(filt)
            self._leaning = leaning.library(self.problem, clusters(g.points.points), g)
        return self._leaning

    def _assemblies(self, filt: ParticleFilter, base: np.ndarray, beam_width: int = assemble.BEAM) -> np.ndarray:
        """``assemble.assemblies`` of the library on ``base`` (K, 4, 4) -> (A, K, 4, 4). The candidates are
        rendered here, in the main process, by a renderer made for the call."""
        with filt.clock.stage("assemblies"):
            return self._assemble(filt, base, beam_width)

    def _assemble(self, filt: ParticleFilter, base: np.ndarray, beam_width: int) -> np.ndarray:
        g = self.geometry(filt)
        renderer = DepthRenderer(self.problem.render_camera, [m.mesh for m in self.problem.models],
                                 self.problem.config.render)
        try:
            if self._clashes is None:
                self._clashes = assemble.Clashes(g.solids)
            return assemble.assemblies(self.problem, self.library, renderer, self._clashes, base,
                                       np.argsort(-g.radius, kind="stable"), floored=filt.floor_in,
                                       beam_width=beam_width)
        finally:
            renderer.close()

    def polish(self, filt: ParticleFilter) -> Update:
        """Evaluate the estimate's one- and two-object variants (``polish.variants``), the stacks it could be
        (``polish.stacked``) and the assemblies -> the update: all of them offered for the estimate, those that beat
        it to replace the worst particles (at most a tenth of them)."""
        if filt.estimate is None or self.library is None:
            return Update()
        with filt.clock.stage("polish"):
            return self._polish(filt)

    def _polish(self, filt: ParticleFilter) -> Update:
        g, estimate = self.geometry(filt), filt.estimate
        # The estimate stuck since the last polish: leaning starts, and a wider beam. A leaning object is rare, and
        # a real desk's clutter shows slanted patches: tried at every polish, leaning starts win early on clutter and
        # send the search elsewhere.
        stuck = filt.estimate_loglik - self.polished_at < STUCK
        self.polished_at = filt.estimate_loglik
        key = polish_key(filt)
        if key != self.offered_for:
            self.offered_for, self.offered = key, set()
        parts = [polish.variants(estimate, self.library, g, self.unexplained, hiding.hider(self.problem, g),
                                 polish.gains(self.problem, estimate, g.samples),
                                 self.leaning_starts(filt) if stuck else None),
                 polish.stacked(self.problem, estimate, self.library, self.unexplained, g, self._base_memo,
                                partial(self._run, filt))]
        beam = assemble.WIDE_BEAM if stuck else assemble.BEAM
        lib = self.library
        made = f"assemblies {beam} " + checksum({**{f"poses {k}": P for k, P in enumerate(lib.poses)},
                                                 **{f"weights {k}": w for k, w in enumerate(lib.weights)}})
        joint = np.zeros((0, *estimate.shape)) if made in self.offered else self._assemblies(filt, estimate, beam)
        self.offered.add(made)
        parts = [new_scenes(p.reshape(-1, *estimate.shape), self.offered) for p in parts + [joint]]
        joint = parts[-1]
        kinds = np.repeat(np.array([MoveKind.POLISH, MoveKind.BASE, MoveKind.ASSEMBLE], np.int8),
                          [len(p) for p in parts])
        scenes = np.concatenate(parts)
        if not len(scenes):
            return Update()
        ev = filt.evaluate(scenes)
        # The assemblies and one-object moves to other places that nearly beat the estimate, fitted to the depth
        # (``fit_near_misses``); each fitted assembly also with one of its objects kept where the estimate has it.
        n_variants, joint_ll = len(parts[0]), ev.loglik[len(scenes) - len(joint):]
        assemblies, ones = fit_near_misses(filt, [(joint, joint_ll, 2, FIT_ASSEMBLIES),
                                                  (parts[0], ev.loglik[:n_variants], 1, FIT_MOVES)], estimate,
                                           self.fitted)
        kept = np.concatenate([assemble.one_kept(f, estimate) for f in assemblies] + [ones[:0]])
        fitted = np.concatenate([assemblies, ones, kept])
        if len(fitted):
            scenes = np.concatenate([scenes, fitted])
            kinds = np.append(kinds, np.repeat(np.array([MoveKind.ASSEMBLE, MoveKind.POLISH, MoveKind.ASSEMBLE],
                                                        np.int8), [len(assemblies), len(ones), len(kept)]))
            ev = Evaluation.concatenate([ev, filt.evaluate(fitted)])
        better = np.nonzero(ev.loglik > filt.estimate_loglik)[0]
        better = better[np.argsort(-ev.loglik[better], kind="stable")][: max(1, len(filt.particles) // 10)]
        return Update(offered=(ev, kinds), replacements=ParticleSet.evaluated(scenes, ev, kinds)[better])


def polish_key(filt: ParticleFilter) -> str:
    """What a polish's evaluations depend on besides the scenes themselves: the estimate (K, 4, 4), the sink and
    whether the clutter floor counts."""
    return f"{checksum({'estimate': filt.estimate})} {filt.sink!r} {filt.floor_in}"


def new_scenes(scenes: np.ndarray, offered: set[str]) -> np.ndarray:
    """Of ``scenes`` (S, K, 4, 4), those whose ``checksum`` is not in ``offered`` (nor an earlier one of them), in
    their order -> (S', K, 4, 4); ``offered`` gets their checksums."""
    keep = []
    for i, scene in enumerate(scenes):
        d = checksum({"scene": scene})
        if d not in offered:
            offered.add(d)
            keep.append(i)
    return scenes[keep]
