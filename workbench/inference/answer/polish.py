"""Polish: systematic one- and two-object changes of the estimate itself.

The particle moves change one object of a *random* particle at a time, so a change that the estimate needs (its
mustard bottle put on the candidate where the data shows it; two objects that took each other's places exchanged)
is tried on the estimate only by chance; nor can a Gaussian step turn an object that came to rest turned by 180
degrees about the vertical (a mustard bottle with its nozzle to the wrong side) and shifted to fit that way, nor
put a hidden base under the top it carries (``stacked``). Every time the candidates are refitted, these variants of
the estimate are evaluated like any hypothesis (physics, then the likelihood). A variant that beats the estimate
becomes the estimate and replaces the worst particles, so the particle set searches on from it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from workbench.evaluation import run_here
from workbench.geometry import rot_z, rotation_angle
from workbench.inference.search.datadriven import (
    Library,
    fit_scores,
    overlaps,
    place_order,
)
from workbench.inference.search.hiding import Hide
from workbench.inference.search.moves.resting import (
    highest_point,
    lowest_point,
)
from workbench.inference.search.moves.stacking import BASE_MIN, bases_under
from workbench.inference.search.refine import refit
from workbench.inference.search.scenepoints import ModelSamples, unclaimed
from workbench.problem.problem import Problem

if TYPE_CHECKING:  # annotations only: the geometry module imports this one's neighbours
    from workbench.inference.search.geometry import SearchGeometry

MEMO_LIMIT = 2000  # tops whose bases ``stacked`` remembers
MEMO_CELL = 0.01  # m; tops whose centres and bottoms fall in one cell of this size share their bases
PER_OBJECT = 6  # candidates of each object tried in place of its pose in the estimate: the best of as many places
LEANING_PER_OBJECT = 3  # and of its leaning starts (``leaning.library``): the best of as many patches
# A candidate this close to the estimate's pose is no change; this close to one already tried, no new variant.
SAME_M, SAME_RAD = 0.01, np.radians(10.0)
LIFT = 0.005  # m; exchanged objects start this far above their old height, and physics sets them down

Gain = Callable[[int, np.ndarray], np.ndarray]  # (object k, its candidate poses (C, 4, 4)) -> what each adds (C,)


def variants(estimate: np.ndarray, library: Library, geometry: SearchGeometry, unexplained: Library | None = None,
             hide: Hide | None = None, gain: Gain | None = None, leaning: Library | None = None) -> np.ndarray:
    """Variants of the estimate (K, 4, 4), with the objects' ``geometry``:
    - one object turned by 90, 180 or 270 degrees about the vertical through its centre and refitted by ICP to the
      observed points near it (``refine.refit``);
    - one object put on its best library candidate at one of its ``PER_OBJECT`` best places
      (``datadriven.place_order``), for every object and candidate that differs from its pose in the estimate,
      the objects it would sit inside moved out of its way (``seat``); the candidates of
      ``unexplained`` (the latest refit alone: fitted to what the estimate leaves unexplained) are tried first,
      at their own ``PER_OBJECT`` best places; with ``gain`` (``gains``), the best places by what each candidate
      adds to the rest of the estimate, not by its weight; then its leaning starts at its LEANING_PER_OBJECT
      best places in ``leaning`` (``leaning.library``); with ``hide`` (``hiding.hider``), each such variant
      that moves objects out of the way also with those objects at their hiding places instead (``seat``);
    - every pair of objects exchanging their places (x, y), each keeping its own orientation and height.
    -> (V, K, 4, 4), V <= K * (4 PER_OBJECT + 2 LEANING_PER_OBJECT + 3) + K (K - 1) / 2."""
    K = len(estimate)
    cloud, samples, reach, radii = geometry.points, geometry.samples, geometry.reach, geometry.radius
    out = []
    for k in range(K):
        turned = np.repeat(estimate[k][None], 3, axis=0)
        turned[:, :3, :3] = rot_z(np.pi / 2 * np.arange(1, 4)) @ estimate[k, :3, :3]
        for T in refit(cloud, samples[k], reach[k], turned):
            scene = estimate.copy()
            scene[k] = T
            out.append(scene)
    for k in range(K):
        # The merged library ranks places by how many points a candidate explains, and a large cluster holds many
        # places: YCB-Video's standing marker, parked 50 cm away by the search (frame 2:20), had its right
        # candidates in the library from the first refit on, behind the large cluster's places, and polish never
        # put it back (+500 log-units). The latest refit sees only what the estimate leaves unexplained.
        for T in _poses_tried(estimate, k, library, unexplained, gain, leaning)[1:]:
            out.append(seat(estimate, {k: T}, library, radii))
            hidden = seat(estimate, {k: T}, library, radii, hide) if hide is not None else out[-1]
            if not np.array_equal(hidden, out[-1]):
                out.append(hidden)
    for i in range(K):
        for j in range(i + 1, K):
            scene = estimate.copy()
            scene[i, :2, 3], scene[j, :2, 3] = estimate[j, :2, 3], estimate[i, :2, 3]
            scene[[i, j], 2, 3] += LIFT
            out.append(scene)
    return np.array(out).reshape(-1, K, 4, 4)


def stacked(problem: Problem, estimate: np.ndarray, library: Library, unexplained: Library | None,
            geometry: SearchGeometry, memo: dict, run: Callable | None = None) -> np.ndarray:
    """Variants of the estimate (K, 4, 4) that build a stack: a top object on a candidate that does not rest on
    the table (its pose in the estimate, or one tried by ``variants``), and under it, as its base, every other
    object at each of its best places there (``stacking.bases_under``: by their resting faces, convex hulls and
    surface samples in ``geometry``); the top is lifted onto a base taller than its bottom,
    and the objects either would sit inside are seated elsewhere (``seat``). ``memo`` keeps each
    top's bases between calls (the library changes slowly); ``run(fn, calls)`` runs the base searches
    (``Evaluator.map``; default ``evaluation.run_here``). -> (V, K, 4, 4).

    No one-object change can build such a stack when the base is hidden: the base alone, wherever it goes, explains
    almost nothing, and the top alone on its candidate floats and falls."""
    K = len(estimate)
    rest, hulls, samples, radii = geometry.rest, geometry.hulls, geometry.samples, geometry.radius
    out = []
    if len(memo) > MEMO_LIMIT:
        memo.clear()
    tops = []  # (k, top pose, its bottom's height, memo key)
    for k in range(K):
        for T in _poses_tried(estimate, k, library, unexplained):
            bottom = T[2, 3] + lowest_point(T[:3, :3], hulls[k])
            if bottom >= BASE_MIN:
                # Where the bases go depends on the top only through its centre and how high its bottom is; tops
                # within MEMO_CELL of each other (the candidates shift by millimetres between refits) share them.
                cell = np.round(np.array([*T[:2, 3], bottom]) / MEMO_CELL).astype(int)
                tops.append((k, T, bottom, (k, *cell.tolist())))
    # The base searches of the tops not remembered (the first top of each key), all at once: ``run`` may spread
    # them over the workers.
    searched: dict[tuple, tuple[int, np.ndarray]] = {}
    for k, T, _, key in tops:
        if key not in memo:
            searched.setdefault(key, (k, T))
    calls = [(key, j) for key, (k, _) in searched.items() for j in range(K) if j != k]
    found = (run or run_here(problem))(bases_under, [(searched[key][1], hulls[searched[key][0]], rest[j], hulls[j],
                                                      samples[j]) for key, j in calls])
    for key in searched:
        memo[key] = []
    for (key, j), bases in zip(calls, found):
        memo[key] += [(j, B) for B, _ in bases]
    for k, T, bottom, key in tops:
        for j, B in memo[key]:
            top = T.copy()
            summit = B[2, 3] + highest_point(B[:3, :3], hulls[j])
            top[2, 3] += max(0.0, summit - bottom) + LIFT
            out.append(seat(estimate, {k: top, j: B}, library, radii))
    return np.array(out).reshape(-1, K, 4, 4)


def _poses_tried(estimate: np.ndarray, k: int, library: Library, unexplained: Library | None,
                 gain: Gain | None = None, leaning: Library | None = None) -> list[np.ndarray]:
    """Object k's pose in the estimate (K, 4, 4), then its candidates (4, 4) at its best places in ``unexplained``,
    in ``leaning`` (the first LEANING_PER_OBJECT) and in ``library`` (``_best_places``), each unlike those before
    it (``_same``)."""
    tried = [estimate[k]]
    leans = _best_places(leaning, k, gain)[:LEANING_PER_OBJECT]
    for T in _best_places(unexplained, k, gain) + leans + _best_places(library, k, gain):
        if not any(_same(T, U) for U in tried):
            tried.append(T)
    return tried


def _same(T: np.ndarray, U: np.ndarray) -> bool:
    """Whether poses T and U (4, 4) are one (SAME_M, SAME_RAD)."""
    return bool(np.linalg.norm(T[:3, 3] - U[:3, 3]) < SAME_M and rotation_angle(T[:3, :3].T @ U[:3, :3]) < SAME_RAD)


def _best_places(library: Library | None, k: int, gain: Gain | None = None) -> list[np.ndarray]:
    """Object k's candidates (4, 4) at its ``PER_OBJECT`` best places in ``library`` (none if there is none), by
    ``gain`` (k, poses) -> (C,) when given, else by their weights."""
    if library is None or not library.has(k):
        return []
    P = library.poses[k]
    return list(P[place_order(P, library.weights[k] if gain is None else gain(k, P))[:PER_OBJECT]])


def gains(problem: Problem, estimate: np.ndarray, samples: list[ModelSamples]) -> Gain:
    """What a candidate adds to the rest of the ``estimate`` (K, 4, 4): ``gain(k, poses)`` (C, 4, 4) -> (C,) its fit
    score (``datadriven.fit_scores``) against the observed depth less the pixels the estimate's other objects
    explain (``scenepoints.unclaimed``, made once per object).

    Why: a candidate's weight counts every pixel it explains, so a flat box's fits on other objects' tops outrank
    its fit where nothing else is: on real-shape frame 5 the gelatin box, parked 46 cm away, had a candidate 0.6 cm
    from its truth (126 log-units above the estimate put there) at its 8th best place by weight, and polish tries
    the best 6."""
    left: dict[int, np.ndarray] = {}

    def gain(k: int, poses: np.ndarray) -> np.ndarray:
        if k not in left:
            left[k] = unclaimed(problem, estimate, samples, k)
        return fit_scores(problem, poses, samples[k], observed=left[k])
    return gain


def seat(scene: np.ndarray, changes: dict[int, np.ndarray], library: Library, radii: np.ndarray,
         hide: Hide | None = None) -> np.ndarray:
    """``scene`` (K, 4, 4) with each object k of ``changes`` at its pose (4, 4) there, and every object one of them
    would then sit inside (``overlaps``; ``radii`` (K,) m) moved to its first candidate in ``place_order`` clear of
    all the others, else of the objects already seated; an object moved so may push out the next (an ejection
    chain, each object moved at most once). With ``hide`` (``hiding.hider``), an object pushed out goes to its
    hiding place behind the object that pushed it out instead. -> (K, 4, 4).

    An estimate that went wrong early is often a chain of objects each on another's place: on YCB-Video frame
    2:10 the pudding box sat on the potted meat can's place and the marker on the banana's, the can and the banana
    lay 50 cm away on flat clutter. Putting the can back alone leaves it inside the pudding box, which physics
    pushes both out of, so no one-object change could gain; with the pudding box moved aside in the same variant,
    the chain unwinds one link per polish."""
    out = scene.copy()
    for k, T in changes.items():
        out[k] = T
    K = len(out)
    seated = list(changes)
    queue = list(changes)
    while queue:
        i = queue.pop(0)
        for j in range(K):
            if j in seated or not overlaps(out[j], out[[i]], radii[j], radii[[i]]):
                continue
            seated.append(j)
            if hide is not None:
                out[j] = hide(out, j, i)
                queue.append(j)
                continue
            if not library.has(j):
                continue
            others = np.array([o for o in range(K) if o != j], dtype=int)
            done = np.array(seated[:-1], dtype=int)
            order = place_order(library.poses[j], library.weights[j])
            clear = [c for c in order if not overlaps(library.poses[j][c], out[others], radii[j], radii[others])]
            clear = clear or [c for c in order if not overlaps(library.poses[j][c], out[done], radii[j], radii[done])]
            if clear:
                out[j] = library.poses[j][clear[0]]
                queue.append(j)
    return out
