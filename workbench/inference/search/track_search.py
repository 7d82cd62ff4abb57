"""The search of a tracked frame: the previous frame's particles and estimate carried into this one, a short local
search around them, and a light settle.

A sequence keeps one table frame (``track``), so objects that do not move keep their poses and the previous
frame's particle set is this frame's prior as it stands (the paper's Eq. 1 with a static-scene motion model). The
default search's hooks, narrowed:

- ``start``: the carried particles resampled by their weights, the carried estimate and its settled answer among
  them, scored as they are: they rest already, on the same table, so physics would only move them by its own
  noise, at several times the cost of scoring them. The step after it moves them. Where objects are found lost
  (``lost``), each object is jittered by Sigma and projected, and the lost ones are drawn from data-driven
  candidates fitted to what the carried scene leaves unexplained.
- ``propose``: the default search's, with the tracked frame's move mix (local moves; data moves when re-searching).
- ``after_step``: the default search's polish only while re-searching lost objects.
- ``finish``: each object settled alone on this frame's depth from its last answer (``settle_each``) and kept
  there unless the depth clearly moves it (a static scene stays still), and the previous posterior weighed again on this
  view, its evidence kept (``carried_posterior``: a mode this view decides is gone, one it favours clearly
  replaces the estimate); the default search's full finish (half turns, posterior sweep) when re-searching.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from workbench.inference.answer import carried_posterior, settle
from workbench.inference.answer.posterior import Posterior, doubted, hide
from workbench.inference.search import datadriven
from workbench.inference.search.default_search import DefaultSearch
from workbench.inference.search.geometry import SearchGeometry
from workbench.inference.search.moves import gaussian
from workbench.inference.search.moves.registry import MoveKind
from workbench.inference.search.scenepoints import badness, observed_points, seen_counts, unseen
from workbench.inference.smc.filter import ParticleFilter, Settled, Started, Update
from workbench.inference.smc.resampling import systematic_resample
from workbench.problem.problem import Problem

# Log-units a settled object must gain over its last answer to move from it: the estimator's margin for a turn
# (settle.TURN_MARGIN). The depth's noise alone moved settled objects by about a millimetre and a degree from frame
# to frame on ycbv-real-seq (median), for gains of a few log-units; with this margin a still object stays still.
STILL_MARGIN = settle.TURN_MARGIN
# Rounds of each object's settling search on a tracked frame (two batches each; 2 mm and 2 degree steps, then 1):
# its last answer is within a few millimetres. Unbounded, one object's walk set the number of round trips of all
# (up to 13 rounds; 21 batches a frame on ycbv-real-seq scene 2, 12 with 4), with the same answers right.
SETTLE_ROUNDS = 4


def settle_each(found: np.ndarray, last: np.ndarray, score: settle.Score, max_shift_m: float, max_turn_deg: float,
                margin: float) -> tuple[np.ndarray, float, int]:
    """The static-scene prior and the light settle at once: each object of the last answer ``last`` (K, 4, 4)
    fitted to this frame's depth alone, the others kept at their last answers, from the better of its last answer
    and its pose in this frame's estimate ``found`` (K, 4, 4); the objects' searches run in lockstep (one batch per
    round for all of them). An object whose fit gains more than ``margin`` log-units over its last answer takes it,
    the others keep their last answers -> (the scene, its log-likelihood, scenes scored)."""
    K = len(last)
    probe = np.repeat(last[None], K + 1, axis=0)
    probe[np.arange(1, K + 1), np.arange(K)] = found
    ll = score(probe)
    base, scored = float(ll[0]), K + 1
    searches = []
    for k in range(K):
        start = probe[k + 1] if ll[k + 1] > base else last
        searches.append(settle.search(start, step_m=settle.SETTLE_STEP / 2, step_deg=settle.SETTLE_DEGREES / 2,
                                      min_step_m=0.001, max_rounds=SETTLE_ROUNDS, max_shift_m=max_shift_m,
                                      max_turn_deg=max_turn_deg, objects=[k]))
    out = last.copy()
    for k, (T, fitted, n) in enumerate(settle.run(searches, score)):
        scored += n
        if fitted > base + margin:
            out[k] = T[k]
    if np.array_equal(out, last):
        return out, base, scored
    return out, float(score(out[None])[0]), scored + 1


@dataclass(frozen=True)
class Carried:
    """What a frame hands the next, table frame, m: the final ``particles`` (N, K, 4, 4) as physics rested them
    with their ``weights`` (N,); the filter's ``estimate`` (K, 4, 4) and the ``settled`` answer (K, 4, 4); the
    ``sink`` (m); the candidate ``library`` (or None); the ``posterior`` (or None); the search ``geometry``, whose
    per-model parts every frame shares; ``badness`` (K,): how badly each object of ``settled`` explained its part of
    that frame (``scenepoints.object_badness``), the reference a later frame's fit is judged against; ``lost`` (K,)
    bool or None: objects that frame lost and did not find again, carried where they were last found
    (``held``)."""

    particles: np.ndarray
    weights: np.ndarray
    estimate: np.ndarray
    settled: np.ndarray
    sink: float
    library: datadriven.Library | None
    posterior: Posterior | None
    geometry: SearchGeometry
    badness: np.ndarray
    lost: np.ndarray | None = None

    def held(self, before: "Carried", lost: np.ndarray) -> "Carried":
        """This frame's state with the ``lost`` objects ((K,) bool) put back where ``before`` (the state this frame
        started from, same table frame) had them: its answer, estimate, every particle, badness and posterior. An
        object taken out of the scene, or one the re-search could not find, is looked for again on the next frame
        where it was last seen: put back there, it is explained at once (recovered); else it is lost again."""
        lost = np.asarray(lost, dtype=bool)
        if not lost.any():
            return replace(self, lost=lost)
        settled, estimate, particles = self.settled.copy(), self.estimate.copy(), self.particles.copy()
        settled[lost], estimate[lost] = before.settled[lost], before.estimate[lost]
        particles[:, lost] = before.settled[lost]
        badness = self.badness.copy()
        badness[lost] = before.badness[lost]
        posterior = self.posterior
        if posterior is not None and before.posterior is not None:
            was = {o.obj: o for o in before.posterior.objects}
            posterior = replace(posterior, objects=[was[o.obj] if lost[o.obj] and o.obj in was else o
                                                    for o in posterior.objects])
        return replace(self, particles=particles, estimate=estimate, settled=settled, badness=badness,
                       posterior=posterior, lost=lost)

    def moved(self, A: np.ndarray) -> "Carried":
        """Every pose left-multiplied by ``A`` (4, 4): into another table frame (identity: the same)."""
        if np.allclose(A, np.eye(4), atol=1e-9):
            return self
        library = None if self.library is None else datadriven.Library(
            [A @ p for p in self.library.poses], self.library.weights)
        posterior = None if self.posterior is None else replace(self.posterior, objects=[
            replace(o, modes=[replace(m, T=A @ m.T) for m in o.modes]) for o in self.posterior.objects])
        return replace(self, particles=A @ self.particles, estimate=A @ self.estimate, settled=A @ self.settled,
                       library=library, posterior=posterior)


class TrackSearch(DefaultSearch):
    """The default search narrowed to a tracked frame (module docstring); ``lost``: indices of the objects whose
    carried poses no longer explain the observation, re-searched data-driven."""

    def __init__(self, problem: Problem, carried: Carried, lost: list[int]):
        super().__init__(problem)
        self.carried, self.lost = carried, list(lost)
        self.library = carried.library

    def geometry(self, filt: ParticleFilter) -> SearchGeometry:
        """The carried per-model geometry with this frame's observed points."""
        if self._geometry is None:
            self._geometry = replace(self.carried.geometry, points=observed_points(self.problem))
        return self._geometry

    def start(self, filt: ParticleFilter) -> Started:
        cfg, c = filt.config, self.carried
        n, K = cfg.particles, self.problem.n_objects
        idx = systematic_resample(np.log(np.maximum(c.weights, 1e-300)), filt.rng, n)
        start, kinds = c.particles[idx].copy(), np.full(n, int(MoveKind.START), np.int8)
        if self.lost:
            start = gaussian.propose_joint(filt.rng, start, cfg.sigma, np.ones(K), cfg.state).hypotheses
            kinds[:] = int(MoveKind.JOINT)
        start[: min(n, 2)] = np.stack([c.estimate, c.settled])[: min(n, 2)]  # carried as they were
        kinds[: min(n, 2)] = int(MoveKind.START)
        if not self.lost:
            return Started(start, kinds, Update(sink=c.sink), project=False)
        self.refit_library(filt)
        take = np.zeros((n, K), dtype=bool)
        take[2:, self.lost] = filt.rng.random((max(n - 2, 0), len(self.lost))) < cfg.data_start
        start = datadriven.sequential_start(filt.rng, self.library, n, self.geometry(filt).radius, take, start)
        kinds[take.any(axis=1)] = int(MoveKind.DATA_START)
        return Started(start, kinds, Update(sink=c.sink))  # the same table plane: the same sink

    def refit_library(self, filt: ParticleFilter, scene: np.ndarray | None = None) -> None:
        """Only while re-searching lost objects: the carried candidates serve a tracked frame, and refitting them
        costs more than the rest of the frame. Before the first estimate, against the carried scene."""
        if self.lost:
            super().refit_library(filt, self.carried.settled if scene is None and filt.estimate is None else scene)

    def after_step(self, filt: ParticleFilter) -> Iterator[Update]:
        if self.lost:
            yield from super().after_step(filt)

    def finish(self, filt: ParticleFilter) -> Settled:
        """Re-searching: the default search's finish. Tracked: the last answer settled on this frame's depth, object
        by object (``settle_each``), and the carried posterior weighed again (none when the first frame had
        none)."""
        cfg = filt.config
        if self.lost or filt.estimate is None or cfg.settle_shift == 0 or cfg.settle_turn == 0:
            return super().finish(filt)
        score = lambda scenes: filt.evaluate(scenes, project=False).loglik  # noqa: E731
        with filt.clock.stage("settle"):
            scene, loglik, scored = settle_each(filt.estimate, self.carried.settled, score, cfg.settle_shift,
                                                cfg.settle_turn, STILL_MARGIN)
        if self.carried.posterior is None:
            return Settled(scene, loglik, [], scored)

        def refine(scene: np.ndarray, k: int) -> tuple[np.ndarray, float, int]:  # a mode that replaced the estimate
            return settle.pattern_search(
                scene, score, step_m=settle.SETTLE_STEP / 2, step_deg=settle.SETTLE_DEGREES / 2, min_step_m=0.001,
                max_shift_m=cfg.settle_shift, max_turn_deg=cfg.settle_turn, objects=[k])

        with filt.clock.stage("posterior"):
            posterior, scene, loglik, n = carried_posterior.rescored(
                self.problem, scene, loglik, self.carried.posterior, score, filt.particles.projected,
                filt.weights(), refine)
            geometry = self.geometry(filt)
            through, on = seen_counts(self.problem, scene, geometry.samples)
            bad, hid = badness(through, on), unseen(through, on)
            objects = [doubted(o, bad[o.obj]) for o in posterior.objects]
            # An object still hidden keeps its region, its places (about where it is now) scored on this view.
            for o in self.carried.posterior.objects:
                if o.hiding is not None and hid[o.obj]:
                    objects[o.obj], m = hide(objects[o.obj], scene, loglik, score, geometry.solids,
                                             posterior.temperature, o.hiding.places[:, :2] - o.hiding.places[0, :2])
                    n += m
        return Settled(scene, loglik, [], scored + n, replace(posterior, objects=objects))
