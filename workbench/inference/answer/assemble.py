"""Assemble: whole scenes put together from the library, one candidate per object, that jointly explain the
observed depth best without sitting inside each other.

Polish changes the estimate one object (or one exchange) at a time. An estimate that went wrong early is often
several objects each on another's place: on YCB-Video frame 2:10 the pudding box sat on the potted meat can's
place and the marker on the banana's, while the can and the banana lay 50 cm away on flat clutter. Every
one-object change then puts an object inside another, physics pushes both aside, and the change loses thousands of
log-units. A beam search over the candidates finds the joint assignment directly. Each candidate is rendered once,
alone; an assignment's depth is the nearest of its candidates' depths per pixel (what rendering them together
draws) and is scored by the likelihood itself. Assignments in which one candidate sits inside another's hull are
ruled out, since the likelihood cannot see a hidden overlap and physics would push the two apart.

The best few assignments are then evaluated like any hypothesis (physics, then the likelihood).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from workbench.geometry import invert_pose
from workbench.inference.search.datadriven import Library
from workbench.inference.search.geometry import Solid
from workbench.problem.problem import Problem
from workbench.render.depth import DepthRenderer
from workbench.render.likelihood import ImageTerms
from workbench.render.shared import keep_nearer

BEAM = 32  # partial assignments kept after each object
WIDE_BEAM = 64  # ... when the search is stuck (32 lost the four objects of generated clutter frame 5)
ASSEMBLIES = 4  # complete assignments returned
INSIDE = 0.3  # a candidate with this share of its core inside another's hull sits inside it
MARGIN = 0.005  # m; samples less deep than this inside the other hull are touching it, not inside


def inside_share(Ta: np.ndarray, a: Solid, Tb: np.ndarray, b: Solid) -> np.ndarray:
    """Share of object a's core points inside object b's hull (deeper than MARGIN), pose by pose: Ta (P, 4, 4),
    Tb (P, 4, 4), same frame -> (P,)."""
    rel = invert_pose(Tb) @ Ta  # (P, 4, 4): a's frame into b's
    p = a.points @ np.swapaxes(rel[:, :3, :3], 1, 2) + rel[:, None, :3, 3]  # (P, M, 3)
    depth = p @ b.planes[:, :3].T + b.planes[:, 3]  # (P, M, F)
    return (depth.max(axis=-1) < -MARGIN).mean(axis=-1)


def conflicts(Ta: np.ndarray, a: Solid, Tb: np.ndarray, b: Solid) -> np.ndarray:
    """Whether candidate i of object a (Ta (A, 4, 4)) and candidate j of object b (Tb (B, 4, 4)) sit inside one
    another -> (A, B) bool. Only pairs whose bounding spheres meet are tested."""
    return Clashes([a, b]).between(0, Ta, 1, Tb)


class Clashes:
    """``conflicts`` remembered pose pair by pose pair, for one problem's objects (``solids``). A refit merges its
    new fits into the candidates kept before, so most of an assembly's candidate pairs were tested at the one
    before; testing them again was over a third of the assemblies' time on dev frame 2/1. The same answers as
    ``conflicts``, bit for bit."""

    def __init__(self, solids: list[Solid]):
        self.solids = solids
        self._ids: list[dict[bytes, int]] = [{} for _ in solids]  # per object: a candidate pose's bytes -> its id
        # (k_a, k_b) -> (ids of a, ids of b) int8: 1 they clash, 0 they do not, -1 not tested yet
        self._known: dict[tuple[int, int], np.ndarray] = {}

    def _id(self, k: int, T: np.ndarray) -> np.ndarray:
        ids = self._ids[k]
        return np.array([ids.setdefault(np.ascontiguousarray(t).tobytes(), len(ids)) for t in T], np.intp)

    def _table(self, ka: int, kb: int) -> np.ndarray:
        """The tested pairs of objects ka and kb, grown to every id given so far."""
        shape = (len(self._ids[ka]), len(self._ids[kb]))
        old = self._known.get((ka, kb), np.zeros((0, 0), np.int8))
        if old.shape != shape:
            grown = np.full(shape, -1, np.int8)
            grown[: old.shape[0], : old.shape[1]] = old
            self._known[(ka, kb)] = old = grown
        return old

    def between(self, ka: int, Ta: np.ndarray, kb: int, Tb: np.ndarray) -> np.ndarray:
        """``conflicts`` of object ka's candidates ``Ta`` (A, 4, 4) with object kb's ``Tb`` (B, 4, 4) -> (A, B)
        bool, testing only the pairs not tested before."""
        a, b = self.solids[ka], self.solids[kb]
        out = np.zeros((len(Ta), len(Tb)), bool)
        gap = np.linalg.norm(Ta[:, None, :3, 3] - Tb[None, :, :3, 3], axis=-1)
        i, j = np.nonzero(gap < a.radius + b.radius)
        ida, idb = self._id(ka, Ta)[i], self._id(kb, Tb)[j]
        known = self._table(ka, kb)
        new = known[ida, idb] < 0
        if new.any():
            ni, nj = i[new], j[new]
            clash = (inside_share(Ta[ni], a, Tb[nj], b) > INSIDE) | (inside_share(Tb[nj], b, Ta[ni], a) > INSIDE)
            known[ida[new], idb[new]] = clash
        out[i, j] = known[ida, idb] == 1
        return out


def candidate_depths(renderer: DepthRenderer, poses: np.ndarray, k: int) -> np.ndarray:
    """Depth images (C, H, W) of object k alone at each of ``poses`` (C, 4, 4), table frame: the other objects are
    not drawn."""
    scenes = np.repeat(poses[:, None], renderer.n_objects, axis=1)  # the others' poses are ignored
    drawn = np.zeros((len(poses), renderer.n_objects), dtype=bool)
    drawn[:, k] = True
    return renderer.render(scenes, drawn)


def assemblies(problem: Problem, library: Library, renderer: DepthRenderer, clashes: Clashes,
               base: np.ndarray, order: np.ndarray, floored: bool = True, beam_width: int = BEAM) -> np.ndarray:
    """Up to ASSEMBLIES scenes (A, K, 4, 4), best first: ``base`` (K, 4, 4) with every object that has candidates
    put on one of them, no candidate inside another, by the likelihood of the candidates' joint depth (no
    physics). Objects are assigned in ``order`` (K,) (largest first: they constrain the most), keeping the
    ``beam_width`` best partial assignments after each; the objects not yet assigned are absent (the table shows
    there). ``floored``: false leaves the clutter floor out, as the filter does before ``ParticleFilter.floor_at``.
    ``clashes``: which candidates sit inside one another, of the objects' shapes (a search keeps one from call to
    call)."""
    ks = [int(k) for k in order if library.has(int(k))]
    if not ks:
        return np.zeros((0,) + base.shape)
    poses = [_unique(library.poses[k]) for k in ks]
    depths = [candidate_depths(renderer, P, k).reshape(len(P), -1) for P, k in zip(poses, ks)]
    # Only pixels some candidate covers can change the score (with the clutter floor, the whole of each clutter
    # piece they touch: whether its bare pixels get the floor depends on how much of it is claimed); elsewhere
    # every assignment predicts the table.
    config = problem.config.likelihood if floored else replace(problem.config.likelihood, clutter_floor=None)
    covered = np.any(np.concatenate(depths) > 0, axis=0)
    pieces = problem.clutter.ravel() if config.floored else np.full(len(covered), -1)
    touched = np.unique(pieces[covered & (pieces >= 0)])
    cover = np.nonzero(covered | np.isin(pieces, touched))[0]
    depths = [d[:, cover] for d in depths]
    observed = problem.observed.reshape(1, -1)[:, cover]
    background = problem.background.reshape(1, -1)[:, cover]
    segments = pieces[None, cover]
    terms = ImageTerms.of(observed, background, config, segments)
    clash = {(i, j): clashes.between(ks[i], poses[i], ks[j], poses[j]) for i in range(len(ks)) for j in range(i)}
    empty = np.zeros((1, len(cover)), np.float32)
    beam = [(np.zeros(0, int), empty[0],  # (candidate per assigned object, joint depth, its log-likelihood)
             float(np.sum(terms.scene(empty))))]
    for i in range(len(ks)):
        grown = []  # (log-likelihood, its beam entry, the candidate added)
        for b, (chosen, joint, loglik) in enumerate(beam):
            ok = np.ones(len(poses[i]), bool)
            for j, c in enumerate(chosen):
                ok &= ~clash[(i, j)][:, c]
            # A candidate changes the joint depth only where it is nearer: only those pixels (and, with the floor,
            # the pieces they lie on) are scored again, not every covered pixel of every candidate.
            plain, floor = terms.drawn_over(joint, depths[i][ok])
            grown += [(loglik + float(g), b, c) for g, c in zip(plain + floor, np.nonzero(ok)[0])]
        if not grown:  # every candidate sits inside an assigned object: no consistent assignment from here
            return np.zeros((0,) + base.shape)
        grown.sort(key=lambda g: -g[0])  # stable: ties keep the earlier state and candidate
        beam = [(np.append(beam[b][0], c), _drawn_over(beam[b][1], depths[i][c]), loglik)
                for loglik, b, c in grown[:beam_width]]
    out = []
    for chosen, _, _ in beam[:ASSEMBLIES]:
        scene = base.copy()
        for i, c in enumerate(chosen):
            scene[ks[i]] = poses[i][c]
        out.append(scene)
    return np.array(out)


def _drawn_over(joint: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """The joint depth (P,) float32 with a candidate's ``depth`` (P,) float32 drawn over it: the nearer surface per
    pixel, 0 = none (``keep_nearer``), as a new array."""
    out = depth[None].copy()
    keep_nearer(out, joint)
    return out[0]


def moved(scene: np.ndarray, base: np.ndarray) -> list[int]:
    """The objects whose poses differ between ``scene`` and ``base`` (K, 4, 4), in order."""
    return [k for k in range(len(base)) if not np.allclose(scene[k], base[k])]


def one_kept(scene: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Variants of an assembled ``scene`` (K, 4, 4) that moves three or more objects of ``base`` (K, 4, 4): for each
    object it moves, the scene with that one object kept where ``base`` has it -> (V, K, 4, 4), V = 0 when it
    moves fewer. An assembly puts every object on a candidate, so the right arrangement of some objects can come
    with another moved wrongly: generated clutter frame 5's fitted assembly put four objects right and the fifth,
    right in the estimate, 47 cm away."""
    changed = moved(scene, base)
    out = np.repeat(scene[None], len(changed) if len(changed) >= 3 else 0, axis=0)
    for i, k in enumerate(changed[:len(out)]):
        out[i, k] = base[k]
    return out


def _unique(poses: np.ndarray) -> np.ndarray:
    """The distinct poses of (C, 4, 4), first occurrences in order (merged libraries repeat candidates)."""
    _, first = np.unique(np.round(poses.reshape(len(poses), -1), 9), axis=0, return_index=True)
    return poses[np.sort(first)]
