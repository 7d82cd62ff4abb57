"""A tracked frame's posterior: the previous frame's modes, carried and weighed again on the new view, the evidence
of every view so far kept.

A full posterior sweep (``posterior.sweep``: every object's half turns and headings, each settled) costs seconds;
a tracked frame has about one. The modes the previous frame left open are what this view may decide, so each is
scored again here, as given, with the other objects where the new estimate has them.

Evidence accumulates (issue 31, item 4): a mode's ``gap`` in a carried posterior is the weakest it has been, against
the estimate, on any view since it was found (each view's log-likelihood gap against the estimate as carried, both
scored as given; the least of them kept). Views of one still scene are anything but independent (the same model
errors, the same occlusions), so adding their gaps up would grow sure of whatever the first view could not decide;
taking the weakest keeps a mode that no view has decided at its probability, and one view that decides it (a mug's
handle come into view) decides it from then on.
Probabilities follow from these gaps as in ``posterior.object_modes``; a mode that drops below
``posterior.MIN_PROBABILITY`` is gone. A mode that now beats the estimate by more than the turn margin replaces
it (fitted to the depth by ``refine``; the estimate then becomes one of its modes), as settling's turns do: the
estimate stays the most likely mode. An open range of headings is kept as far as the modes in it are. A hidden
object's region (``posterior.ObjectPosterior.hiding``) is carried by the tracking search, its places scored again
on each view while the object stays unseen (``track_search``).
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from workbench.geometry import rotation_angle
from workbench.inference.answer import settle
from workbench.inference.answer.posterior import (
    MAX_MODES,
    MIN_PROBABILITY,
    RANGE_GAP,
    RANGE_STEP_DEG,
    YAW_STEP_DEG,
    Mode,
    ObjectPosterior,
    Posterior,
    position_spread,
    probabilities,
    yaw_range,
)
from workbench.problem.problem import Problem
from workbench.score.metrics import is_right

LAST_ESTIMATE = "the last frame's estimate"
ESTIMATE = "the estimate"
# A carried mode's pose is a turn about the vertical of the estimate's when their rotations differ by a turn about
# the table's z alone, to within this (degrees): it is then a heading of the open range.
LEVEL_DEG = 5.0
# Modes a carried posterior keeps per object: as many as a frame's (``posterior.MAX_MODES``) and a whole circle of
# an open range's headings (``posterior.RANGE_STEP_DEG`` apart).
CARRIED_MODES = MAX_MODES + int(round(360.0 / RANGE_STEP_DEG))

Refine = Callable[[np.ndarray, int], tuple[np.ndarray, float, int]]  # (scene, object) -> (fitted, loglik, scored)


def rescored(problem: Problem, scene: np.ndarray, loglik: float, previous: Posterior, score: settle.Score,
             projected: np.ndarray, weights: np.ndarray, refine: Refine | None = None
             ) -> tuple[Posterior, np.ndarray, float, int]:
    """The posterior of the settled ``scene`` (K, 4, 4, table frame; ``loglik`` as given) from the ``previous``
    frame's (same table frame): its modes scored again with ``score`` (scenes as given -> log-likelihoods), each
    mode's gap the least of its gaps so far (module docstring); a mode that beats the estimate by more than
    ``settle.TURN_MARGIN`` replaces it, fitted by ``refine`` (scene, object) when given; the position spread from
    this frame's particles (``projected`` (N, K, 4, 4), ``weights`` (N,)) -> (the posterior, the scene (the
    estimate with any mode that replaced it), its log-likelihood, scenes scored)."""
    t0 = time.perf_counter()
    given = [(o.obj, m) for o in previous.objects for m in o.modes]
    scenes = np.repeat(scene[None], len(given), axis=0)
    for i, (k, mode) in enumerate(given):
        scenes[i, k] = mode.T
    ll = score(scenes) if len(scenes) else np.zeros(0)
    scored = len(scenes)
    modes = {o.obj: [(m, float(ll[i])) for i, (j, m) in enumerate(given) if j == o.obj] for o in previous.objects}
    # A carried mode that now beats the estimate by more than the turn margin replaces it (the best such one).
    better = {}
    for k, carried in modes.items():
        best = max(carried, key=lambda c: c[1], default=None)
        if best is not None and best[1] - loglik > settle.TURN_MARGIN and \
                not is_right(scene[k], best[0].T, problem.models[k].symmetries):
            turned = scene.copy()
            turned[k] = best[0].T
            better[k] = (turned, best[1])
    replaced = []
    if better:
        kept, (scene, loglik), n = settle.adopt(scene, better, score)
        scored += n
        for k in kept:
            replaced.append(k)
            if refine is not None:
                scene, loglik, n = refine(scene, k)
                scored += n
        if replaced:  # every mode against the scene as it is now (the estimate replaced is one of them)
            again = np.repeat(scene[None], len(given), axis=0)
            for i, (k, mode) in enumerate(given):
                again[i, k] = mode.T
            ll = score(again)
            scored += len(again)
            modes = {o.obj: [(m, float(ll[i])) for i, (j, m) in enumerate(given) if j == o.obj]
                     for o in previous.objects}
    temperature = previous.temperature
    open_gap = RANGE_GAP * temperature
    objects = []
    for o in previous.objects:
        k = o.obj
        symmetries = problem.models[k].symmetries
        # The evidence so far, against the estimate as it is now: the carried mode that the estimate is (the last
        # estimate, or the mode that replaced it) is the reference. This view's gap too is against that mode as
        # given, not against the estimate as settled: the modes are scored as given, and settling alone gains tens of
        # log-units, which made a mug's hidden handle look decided (docs/journal/2026-12.md, "Evidence alone").
        ref, ref_now = next(((m.gap, now) for m, now in modes[k] if is_right(scene[k], m.T, symmetries)),
                            (0.0, loglik))
        candidates = []
        for m, now in modes[k]:
            if is_right(scene[k], m.T, symmetries):
                continue  # the estimate itself
            what = LAST_ESTIMATE if m.what == ESTIMATE else m.what
            candidates.append((m.T, now, min(m.gap - ref, now - ref_now), what))
        objects.append(ObjectPosterior(
            obj=k, modes=accumulated_modes(scene[k], loglik, candidates, symmetries, temperature),
            position_spread_m=position_spread(projected, weights, scene[k], k),
            yaw_range_deg=None if o.yaw_range_deg is None else headings_open(scene[k], candidates, open_gap)))
    return Posterior(objects, temperature, time.perf_counter() - t0), scene, loglik, scored


def accumulated_modes(estimate: np.ndarray, loglik: float, candidates: list[tuple[np.ndarray, float, float, str]],
                      symmetries: np.ndarray, temperature: float, max_modes: int = CARRIED_MODES) -> list[Mode]:
    """One object's modes: the estimate (4, 4; ``loglik`` this view's) and ``candidates`` (pose, this view's
    log-likelihood, accumulated gap to the estimate, what it is), those the same pose up to ``symmetries`` as the
    estimate or as a candidate with a larger gap merged into it -> at most ``max_modes`` modes of at least
    MIN_PROBABILITY, most likely first, probabilities from the accumulated gaps (``posterior.probabilities``)."""
    modes = [(estimate, loglik, 0.0, ESTIMATE)]
    for T, ll, gap, what in sorted(candidates, key=lambda c: -c[2]):
        if not any(is_right(M, T, symmetries) for M, _, _, _ in modes):
            modes.append((np.array(T, dtype=np.float64), float(ll), float(gap), what))
    gaps = np.array([g for _, _, g, _ in modes])
    p = probabilities(gaps, temperature)
    order = np.argsort(-p, kind="stable")[:max_modes]
    order = order[p[order] >= MIN_PROBABILITY]
    kept = p[order] / p[order].sum()
    return [Mode(modes[i][0], modes[i][1], float(gaps[i]), float(q), modes[i][3]) for i, q in zip(order, kept)]


def heading_deg(estimate: np.ndarray, T: np.ndarray) -> float | None:
    """How far (degrees, in (-180, 180]) ``T`` (4, 4) is turned about the table's vertical from ``estimate``, or
    None when it is not such a turn (``LEVEL_DEG``)."""
    R = T[:3, :3] @ estimate[:3, :3].T
    yaw = np.arctan2(R[1, 0], R[0, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    if np.degrees(rotation_angle(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T @ R)) > LEVEL_DEG:
        return None
    return float(np.degrees(yaw))


def headings_open(estimate: np.ndarray, candidates: list[tuple[np.ndarray, float, float, str]], open_gap: float
                  ) -> tuple[float, float] | None:
    """The range of headings about the vertical (degrees about ``estimate``'s) that the modes still leave open:
    every ``YAW_STEP_DEG`` heading takes the accumulated gap of the candidate turned nearest to it (within half a
    step; none: ruled out), and ``posterior.yaw_range`` finds the open arc through the estimate's own, if any."""
    angles = np.arange(YAW_STEP_DEG, 360.0, YAW_STEP_DEG)
    angles = np.where(angles > 180.0, angles - 360.0, angles)
    gaps = np.full(len(angles), -np.inf)
    for T, _, gap, _ in candidates:
        a = heading_deg(estimate, T)
        if a is None:
            continue
        off = np.abs((angles - a + 180.0) % 360.0 - 180.0)
        i = int(np.argmin(off))
        if off[i] <= YAW_STEP_DEG / 2:
            gaps[i] = max(gaps[i], gap)
    return yaw_range(angles, gaps, np.ones(len(angles), dtype=bool), YAW_STEP_DEG, open_gap)
