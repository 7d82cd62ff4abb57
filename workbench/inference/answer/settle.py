"""Settle: the last millimetres of a scene, fitted to the observed depth without physics.

Physics projection keeps a scene plausible, but our models of the world are not the world: on the real YCB-Video
frames the annotated objects rest 4-12 mm below the plane fitted to the table's depth, and projecting the true
scene moves the banana by 6 mm and turns it by 5 degrees (docs/journal/2026-11.md). The search's estimate is such a
projected scene, a few millimetres and degrees from what the depth shows. Settling fits it to the depth with a
pattern search on the likelihood of the scene as given, each object kept within a small trust region around its
pose in the estimate, so the physics that chose the scene (support, stacking, what hides what) still holds to
within that region. An object the camera does not see gains nothing from any move and stays where physics put it.
``half_turns`` gives the turns that the depth can hardly tell apart (a can upside down, a bottle facing the other
way), ``quarter_turns`` an object on a face beside the one it rests on (where the view hides how tall it stands),
and ``level_flips`` a flat object turned over (scissors: its outline mirrored about an axis of its own): the
search compares them only after physics, where the same few millimetres of mismatch decide them, so the
estimator settles them too and keeps a turn that wins clearly (``turn_over``); the turns it does not keep but
that score about as well are the estimate's near ties (``Tie``). The pattern search stops in the first shallow
optimum along the table's axes; ``hop`` restarts each object a few degrees away, within the same region, where the
depth often has a better one (a banana tilted and turned at once).

``pattern_search`` is also how a ground-truth label is fitted to the depth (``labels.fit_label``, no region).
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass
from typing import Callable, Generator

import numpy as np

from workbench.evaluation.base import Run
from workbench.geometry import euler_to_matrix, rotation_angle, rotvec_to_matrix
from workbench.problem.problem import Problem
from workbench.score.metrics import is_right

Score = Callable[[np.ndarray], np.ndarray]  # scenes (B, K, 4, 4) as given -> log-likelihoods (B,)
Rest = Callable[[np.ndarray], np.ndarray]  # scenes (B, K, 4, 4) -> the same scenes at rest under physics


@dataclass(frozen=True)
class Scorer:
    """How the answer's searches judge scenes: ``score`` them as given, put them at ``rest`` under physics, and
    stay within ``max_shift_m`` and ``max_turn_deg`` of where each search starts; ``run`` (``Evaluator.map``; None:
    in this process) does work the evaluation workers can do while they would otherwise wait."""

    score: Score
    rest: Rest
    max_shift_m: float
    max_turn_deg: float
    run: Run | None = None

# Settling's first steps, halved down to 0.5 mm: from a projected estimate the optimum is a few millimetres away.
SETTLE_STEP, SETTLE_DEGREES = 0.004, 4.0  # m, degrees
# A half turn of one object (half_turns) replaces it only when the settled scene gains more than this many
# log-units: turning over a symmetric box, which changes nothing the camera sees, and settling it again gained up to
# 24 on the YCB-Video dev frames (docs/journal/2026-11.md, "Settling").
TURN_MARGIN = 30.0
# Settled objects restart this many degrees away about each table axis (``hop``).
HOP_DEGREES = 8.0
# A flat object turned over shows its outline mirrored, and the level axis that turns it back is the outline's, not
# one of the object's own (real-shape frame 25: the scissors' true pose is the estimate's half turn about a level
# axis 18 degrees from its y axis, 35 degrees of heading beyond settling's reach from either axis's turn). So a flat
# object is also turned about this many level axes, evenly spread: a half turn about an axis d degrees off turns
# the heading by 2d, so at 7.5 degrees apart each lands within 7.5 degrees of any other, inside settling's reach.
FLIP_AXES = 24


@dataclass(frozen=True)
class Tie:
    """A pose of one object that the depth can hardly tell from the estimate's: one of its turns (``half_turns``: a
    can upside down, a marker end for end; ``quarter_turns``: a box on end or lying down), settled, that scores
    within TURN_MARGIN of the estimate's pose with the other objects kept, and is not the same pose up to the
    model's symmetries. The estimator keeps a turn only when it wins by more than TURN_MARGIN, so for such an object
    the depth did not decide: another view, or the object's texture, must."""

    obj: int  # index into problem.models
    turn: str  # half_turn_names, quarter_turn_names: "about the vertical", "a quarter over its x axis", ...
    T: np.ndarray  # (4, 4) the tied pose, table frame, m
    gap: float  # log-units: the scene with this pose minus the scene with the estimate's (as given, not projected)

    def describe(self, problem: Problem) -> str:
        """e.g. "002_master_chef_can turned over its x axis (-3.1 log-units)"."""
        return f"{problem.models[self.obj].name} turned {self.turn} ({self.gap:+.1f} log-units)"


_AXES = list(itertools.product(range(3), (1.0, -1.0)))  # single_moves' order: +x, -x, +y, -y, +z, -z


@functools.lru_cache(maxsize=64)
def _axis_turns(step_rad: float) -> np.ndarray:
    """The rotations by +-``step_rad`` about the table's x, y, z axes, in ``_AXES`` order -> (6, 3, 3), read-only.
    A search asks for the same few steps thousands of times."""
    turns = np.stack([euler_to_matrix(np.eye(3)[axis] * sign * step_rad) for axis, sign in _AXES])
    turns.flags.writeable = False
    return turns


def single_moves(T: np.ndarray, step_m: float, step_rad: float, objects: np.ndarray | None = None) -> np.ndarray:
    """Every single-coordinate move of one object: +-step along the table's x, y, z, and +-step rotations about
    table axes through the object's origin (as ``inference.search.moves.gaussian``). (K, 4, 4) -> (K, 12, K, 4, 4);
    only the ``objects`` (K,) bool that are True are moved (the others' moves are left as ``T``, not to be
    scored)."""
    K = len(T)
    out = np.broadcast_to(T, (K, 12, K, 4, 4)).copy()
    turns = _axis_turns(float(step_rad))  # the same for every object
    for k in range(K) if objects is None else np.flatnonzero(objects):
        for j, (axis, sign) in enumerate(_AXES):
            out[k, j, k, axis, 3] += sign * step_m
            out[k, 6 + j, k, :3, :3] = turns[j] @ T[k, :3, :3]
    return out


def within(moved: np.ndarray, origin: np.ndarray, max_shift_m: float, max_turn_rad: float) -> np.ndarray:
    """Whether poses ``moved`` (..., 4, 4) lie within ``max_shift_m`` (m, between origins) and ``max_turn_rad`` of
    poses ``origin`` (broadcastable to ``moved``) -> (...) bool."""
    shift = np.linalg.norm(moved[..., :3, 3] - origin[..., :3, 3], axis=-1)
    turn = rotation_angle(np.swapaxes(origin[..., :3, :3], -1, -2) @ moved[..., :3, :3])
    return (shift <= max_shift_m) & (turn <= max_turn_rad)


def half_turns(T: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """One object's pose ``T`` (4, 4) turned by 180 degrees about the vertical and about each of its two most
    horizontal axes, through its ``centre`` (3,) (object frame, m) -> (3, 4, 4). These are the depth's near ties:
    a can upside down, a potted meat can or a mustard bottle facing the other way, a marker end for end."""
    axes = _levelled_axes(T[:3, :3])
    return _turned(T, centre, [_half_turn(axis) for axis in [np.array([0.0, 0.0, 1.0]), *axes]])


def quarter_turns(T: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """One object's pose ``T`` (4, 4) turned by +90 and -90 degrees over each of its two most horizontal axes,
    through its ``centre`` (3,) (object frame, m) -> (4, 4, 4), in ``quarter_turn_names`` order: the object on the
    faces beside the one it rests on. Where the view hides how tall an object stands, a box on end and one lying
    down differ by little it sees (real-shape frame 26: the potted meat can stood on its end, 84 degrees off; a
    quarter turn over its own y axis, settled, lands 1 degree from the truth, 317 above)."""
    turns = [rotvec_to_matrix(axis * sign * np.pi / 2) for axis in _levelled_axes(T[:3, :3]) for sign in (1.0, -1.0)]
    return _turned(T, centre, turns)


def quarter_turn_names(T: np.ndarray) -> list[str]:
    """What each of ``quarter_turns(T, ...)`` does, in its order, in words, e.g. "a quarter over its x axis",
    "a quarter back over its x axis"."""
    return [f"a quarter{way} over its {'xyz'[i]} axis" for i in _level_axes(T[:3, :3]) for way in ("", " back")]


def _half_turn(axis: np.ndarray) -> np.ndarray:
    """The rotation (3, 3) by 180 degrees about the unit ``axis`` (3,)."""
    return 2.0 * np.outer(axis, axis) - np.eye(3)


def _turned(T: np.ndarray, centre: np.ndarray, rotations) -> np.ndarray:
    """One object's pose ``T`` (4, 4) turned by each of ``rotations`` (n of (3, 3), table frame) about its
    ``centre`` (3,) (object frame, m), which stays where it is -> (n, 4, 4)."""
    c = T[:3, :3] @ centre + T[:3, 3]
    out = np.repeat(T[None], len(rotations), axis=0)
    for i, H in enumerate(rotations):
        out[i, :3, :3] = H @ T[:3, :3]
        out[i, :3, 3] = H @ (T[:3, 3] - c) + c
    return out


def _levelled_axes(R: np.ndarray) -> np.ndarray:
    """The two object axes (columns of ``R`` (3, 3)) nearest the table plane, laid onto it: unit (2, 3), z = 0."""
    axes = R[:, _level_axes(R)].T.copy()
    axes[:, 2] = 0.0
    return axes / np.linalg.norm(axes, axis=1, keepdims=True)


def _level_axes(R: np.ndarray) -> np.ndarray:
    """Indices of the two object axes (columns of ``R`` (3, 3)) nearest the table plane -> (2,)."""
    return np.argsort(np.abs(R[2]))[:2]


def is_flat(T: np.ndarray, vertices: np.ndarray) -> bool:
    """Whether an object with mesh ``vertices`` (V, 3) (object frame, m) lies flat in pose ``T`` (4, 4): at most
    ``footprint.THIN`` tall and ``footprint.THIN_RATIO`` times as long along a table axis (scissors, a clamp)."""
    from workbench.inference.search.footprint import THIN, THIN_RATIO

    p = vertices @ T[:3, :3].T
    tall = float(np.ptp(p[:, 2]))
    return tall <= THIN and float(np.ptp(p[:, :2], axis=0).max()) >= THIN_RATIO * tall


def level_flips(T: np.ndarray, centre: np.ndarray, n: int = FLIP_AXES) -> tuple[np.ndarray, list[str]]:
    """One object's pose ``T`` (4, 4) turned by 180 degrees about ``n`` level axes through its ``centre`` (3,)
    (object frame, m), their headings spread evenly from its first level axis (``_level_axes``) but for that axis
    and the ones within half a spacing of the second, whose turns ``half_turns`` gives -> (poses (m, 4, 4), the
    name of each turn, e.g. "over a level axis 68 degrees from its x axis")."""
    R = T[:3, :3]
    first, second = _level_axes(R)
    headings = [float(np.arctan2(R[1, i], R[0, i])) for i in (first, second)]
    spacing = np.pi / n
    rotations, names = [], []
    for i in range(1, n):
        h = headings[0] + i * spacing
        off_second = abs((h - headings[1] + np.pi / 2) % np.pi - np.pi / 2)
        if off_second < spacing / 2:
            continue
        rotations.append(_half_turn(np.array([np.cos(h), np.sin(h), 0.0])))
        names.append(f"over a level axis {np.degrees(i * spacing):.0f} degrees from its {'xyz'[first]} axis")
    return _turned(T, centre, rotations), names


def half_turn_names(T: np.ndarray) -> list[str]:
    """What each of ``half_turns(T, ...)`` does, in its order, in words: "about the vertical", then e.g.
    "over its x axis" for a half turn about the object's own x axis (as levelled onto the table)."""
    return ["about the vertical", *(f"over its {'xyz'[i]} axis" for i in _level_axes(T[:3, :3]))]


def ridge_moves(T: np.ndarray, ll: np.ndarray, step_m: float, step_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Each object moved along the direction in which the scene gains most, estimated by central differences of
    the log-likelihoods ``ll`` (K, 12) of its ``single_moves`` (-inf: not tried), the largest component one step.
    The depth often improves only along a diagonal (a banana tilted and turned at once): every single move loses
    there, while the difference of each +-pair still points up the ridge. -> (poses (K, 4, 4), which have a
    direction (K,) bool)."""
    plus, minus = ll[:, 0::2], ll[:, 1::2]  # (K, 6): along x, y, z, then about x, y, z (``single_moves``' order)
    tried = np.isfinite(plus) & np.isfinite(minus)
    slope = np.where(tried, plus - np.where(tried, minus, 0.0), 0.0)
    largest = np.abs(slope).max(axis=1)
    d = slope / np.maximum(largest, 1e-300)[:, None]
    out = np.array(T, dtype=np.float64, copy=True)
    out[:, :3, 3] += step_m * d[:, :3]
    out[:, :3, :3] = rotvec_to_matrix(step_rad * d[:, 3:]) @ out[:, :3, :3]
    return out, largest > 0


Search = Generator[np.ndarray, np.ndarray, tuple[np.ndarray, float, int]]


def search(T: np.ndarray, step_m: float = 0.01, step_deg: float = 4.0, min_step_m: float = 5e-4,
           max_rounds: int = 80, max_shift_m: float = np.inf, max_turn_deg: float = np.inf,
           objects: list[int] | None = None, give_up_below: float = -np.inf,
           known: Callable[[np.ndarray], bool] | None = None, region: np.ndarray | None = None) -> Search:
    """One pattern search from the scene ``T`` (K, 4, 4), as a generator: it yields scenes (B, K, 4, 4) to score as
    given and is sent their log-likelihoods (B,); it returns (the fitted scene, its log-likelihood, how many scenes
    it scored). ``run`` drives it; ``pattern_search`` is the one-search shorthand.

    Each round scores every object's +-step moves along and about the table axes (``single_moves``), then each
    object's ``ridge_moves`` step, and the combinations of every improving object's best single move and of every
    object's ridge step; it keeps the best of all, and halves the steps when nothing improves, down to
    ``min_step_m`` (angles shrink alike). A move that takes an object more than ``max_shift_m`` or
    ``max_turn_deg`` from its pose in ``region`` (K, 4, 4; default ``T``) is not tried; only the ``objects`` listed
    move (default: all). Local: it refines a scene within about two steps of the optimum, it does not find one.

    Two early stops, for the posterior's sweep and settling's turns, which settle many candidates and keep only what
    could be a mode of its own: a search whose best is still below ``give_up_below`` (log-units) once it has
    converged at its first two steps stops there (the finer steps gain a few log-units each, not what it lacks); a
    search that, after its first two steps, moves into a scene that ``known`` (scene (K, 4, 4) -> bool) says is
    already a mode (the estimate's) stops there. Not before: at the first steps a search may pass through a mode on
    its way to another (a mug's heading, 10 degrees from the estimate's and on)."""
    T = np.array(T, dtype=np.float64)
    origin, K = np.array(T if region is None else region, dtype=np.float64), len(T)
    movable = np.zeros(K, dtype=bool)
    movable[np.arange(K) if objects is None else objects] = True
    best, scored = float((yield T[None])[0]), 1
    max_turn = np.radians(max_turn_deg)
    scale = 1.0
    for _ in range(max_rounds):
        if step_m * scale < min_step_m or (scale < 0.5 and best < give_up_below):
            break
        step, turn = step_m * scale, np.radians(step_deg) * scale
        moves = single_moves(T, step, turn, movable)  # (K, 12, K, 4, 4)
        allowed = within(moves[np.arange(K), :, np.arange(K)], origin[:, None], max_shift_m, max_turn)  # (K, 12)
        allowed &= movable[:, None]
        ll = np.full((K, 12), -np.inf)
        if allowed.any():
            ll[allowed] = yield moves[allowed]
            scored += int(allowed.sum())
        # Round two: each object's ridge step alone, all ridge steps together, all improving best moves together.
        ridge, sloped = ridge_moves(T, ll, step, turn)
        sloped &= movable & within(ridge, origin, max_shift_m, max_turn)
        own = ll.argmax(axis=1)
        improving = np.flatnonzero(ll[np.arange(K), own] > best)
        k, j = np.unravel_index(np.argmax(ll), ll.shape)
        candidates, values = ([moves[k, j]], [float(ll[k, j])]) if np.isfinite(ll[k, j]) else ([], [])
        second = []
        for obj in np.flatnonzero(sloped):
            second.append(T.copy())
            second[-1][obj] = ridge[obj]
        if sloped.sum() > 1:
            second.append(T.copy())
            second[-1][sloped] = ridge[sloped]
        if len(improving) > 1:  # with one, the combination is that move, already scored
            second.append(T.copy())
            second[-1][improving] = moves[improving, own[improving], improving]
        if second:
            candidates += second
            values += [float(v) for v in (yield np.stack(second))]
            scored += len(second)
        i = int(np.argmax(values)) if values else -1
        if i >= 0 and values[i] > best:
            T, best = candidates[i], values[i]
            if scale < 0.5 and known is not None and known(T):
                break
        else:
            scale /= 2.0
    return T, best, scored


def run(searches: list[Search], score: Score) -> list[tuple[np.ndarray, float, int]]:
    """Drive ``searches`` in lockstep: every round trip scores the scenes all of them ask for in one call, so many
    small searches (an object's turns, every object's) cost a few batches, not one call per step each -> each
    search's (scene, log-likelihood, scenes scored), in order."""
    results: list = [None] * len(searches)
    asks = {i: next(s) for i, s in enumerate(searches)}  # each search's scenes waiting to be scored
    while asks:
        order = list(asks)
        ll = score(np.concatenate([asks[i] for i in order]))
        at = 0
        for i in order:
            n = len(asks[i])
            try:
                asks[i] = searches[i].send(ll[at:at + n])
            except StopIteration as done:
                results[i] = done.value
                del asks[i]
            at += n
    return results


def pattern_search(T: np.ndarray, score: Score, step_m: float = 0.01, step_deg: float = 4.0,
                   min_step_m: float = 5e-4, max_rounds: int = 80, max_shift_m: float = np.inf,
                   max_turn_deg: float = np.inf, objects: list[int] | None = None) -> tuple[np.ndarray, float, int]:
    """Fit a scene (K, 4, 4) to the depth by ``score`` (the likelihood of scenes as given) -> (the fitted scene,
    its log-likelihood, how many scenes were scored). One ``search``, run on its own."""
    return run([search(T, step_m, step_deg, min_step_m, max_rounds, max_shift_m, max_turn_deg, objects)], score)[0]


Turn = tuple[int, str, np.ndarray, float]  # an object, the name of its turn, the settled scene, its log-likelihood


def turn_over(problem: Problem, scene: np.ndarray, loglik: float, score: Score, rest: Rest, max_shift_m: float,
              max_turn_deg: float, give_up_below: float = -np.inf
              ) -> tuple[np.ndarray, float, int, list[Tie], list[Turn]]:
    """Each object of the settled ``scene`` (K, 4, 4) turned over (``half_turns``), onto the faces beside the one it
    rests on (``quarter_turns``; a flat object also over the best of its ``level_flips``, ``best_level_flips``) and
    settled alone, the others kept: the depth's near ties, which the search compares only after physics, where our
    models' few millimetres of mismatch can decide them. Every object's turns are searched together, in lockstep
    (``run``). An object's best turn is kept when the scene as given gains more than TURN_MARGIN over ``loglik`` and
    physics (``rest``), resting that scene, keeps the object within the settling region; when several objects turn,
    their turns are kept together if that scene scores at least as well as the best one alone -> (scene, log-
    likelihood, scenes scored, the ties left, every settled turn as (object, name, scene, log-likelihood): the
    posterior's turns when no turn was kept). A turn still below ``give_up_below`` once settled at its first two
    steps stops there (``search``): it could neither replace the object nor be reported as a mode."""
    starts, names = [], []
    for k, model in enumerate(problem.models):
        for turns, turn_names in ((half_turns, half_turn_names), (quarter_turns, quarter_turn_names)):
            starts += [(k, pose) for pose in turns(scene[k], model.mesh.bounds.mean(axis=0))]
            names += turn_names(scene[k])
    flips, flip_names, scored = best_level_flips(problem, scene, score)
    starts += flips
    names += flip_names
    owners = [k for k, _ in starts]
    found, best = settle_alone(scene, loglik, score, starts, max_shift_m, max_turn_deg, give_up_below=give_up_below)
    scored += sum(n for _, _, n in found)
    kept, result, n = keep_held(scene, loglik, best, score, rest, max_shift_m, max_turn_deg)
    scored += n
    final = result[0]
    ties = []
    for k, name, (T, ll, _) in zip(owners, names, found):
        gap = ll - kept.get(k, loglik)  # against the same object's pose in the result, the others as settled
        # a turn that lands within the benchmarks' "right" tolerances of the result is the same pose
        if gap > -TURN_MARGIN and not is_right(final[k], T[k], problem.models[k].symmetries):
            ties.append(Tie(k, name, T[k].copy(), float(gap)))
    turns = [(k, name, T, ll) for k, name, (T, ll, _) in zip(owners, names, found)]
    return final, float(result[1]), scored, ties, turns


def best_level_flips(problem: Problem, scene: np.ndarray, score: Score
                     ) -> tuple[list[tuple[int, np.ndarray]], list[str], int]:
    """For each object of ``scene`` (K, 4, 4) that lies flat (``is_flat``), the one of its ``level_flips`` that scores
    best as given, the others kept: where settling starts it turned over its outline's axis -> (starts as
    (object, pose (4, 4)), their names, scenes scored). Settling every flip would cost as many searches. Each turns
    about the mesh's centroid, which its outline follows: about its bounding box's centre the flip that turns the
    generated scissors back landed 2.9 cm off, beyond settling's reach, and scored below 8 wrong ones."""
    starts, names, scored = [], [], 0
    for k, model in enumerate(problem.models):
        if not is_flat(scene[k], model.mesh.vertices):
            continue
        poses, turn_names = level_flips(scene[k], model.mesh.centroid)
        trial = np.repeat(scene[None], len(poses), axis=0)
        trial[:, k] = poses
        i = int(np.argmax(score(trial)))
        scored += len(poses)
        starts.append((k, poses[i]))
        names.append(turn_names[i])
    return starts, names, scored


def small_turns(T: np.ndarray, centre: np.ndarray, degrees: float) -> np.ndarray:
    """One object's pose ``T`` (4, 4) turned by +-``degrees`` about the table's x, y and z axes through its
    ``centre`` (3,) (object frame, m) -> (6, 4, 4), in ``_AXES`` order."""
    return _turned(T, centre, _axis_turns(float(np.radians(degrees))))


def hop(problem: Problem, scene: np.ndarray, loglik: float, score: Score, rest: Rest, region: np.ndarray,
        max_shift_m: float, max_turn_deg: float, objects: list[int], degrees: float = HOP_DEGREES
        ) -> tuple[np.ndarray, float, int]:
    """Each of the ``objects`` of the settled ``scene`` (K, 4, 4), of log-likelihood ``loglik``, restarted from its
    ``small_turns`` and settled alone, the others kept: the pattern search stops in the first shallow optimum along
    the table's axes, and a few degrees away the depth often has a better one (a banana tilted and turned at once,
    a bottle's lean). The restarts stay within ``max_shift_m`` and ``max_turn_deg`` of ``region`` (K, 4, 4: where
    physics put each object, the region settling searched), not of their own start, so that an object is never
    fitted further from physics' pose than settling may fit it; a restart that begins outside it is not tried.
    Every restart is searched in lockstep (``run``); an object's best one is kept on a turn's terms: the scene as
    given gains more than TURN_MARGIN (landings of settling a few tenths of a millimetre apart differ by tens of
    log-units, so a smaller gain is the grid's, not the depth's) and physics (``rest``) keeps it within the region
    -> (scene, log-likelihood, scenes scored)."""
    starts = []
    for k in objects:
        turns = small_turns(scene[k], problem.models[k].mesh.bounds.mean(axis=0), degrees)
        starts += [(k, pose) for pose in turns[within(turns, region[k], max_shift_m, np.radians(max_turn_deg))]]
    found, best = settle_alone(scene, loglik, score, starts, max_shift_m, max_turn_deg, region)
    _, (scene, loglik), n = keep_held(scene, loglik, best, score, rest, max_shift_m, max_turn_deg)
    return scene, float(loglik), sum(n for _, _, n in found) + n


def settle_alone(scene: np.ndarray, loglik: float, score: Score, starts: list[tuple[int, np.ndarray]],
                 max_shift_m: float, max_turn_deg: float, region: np.ndarray | None = None,
                 give_up_below: float = -np.inf
                 ) -> tuple[list[tuple[np.ndarray, float, int]], dict[int, tuple[np.ndarray, float]]]:
    """``scene`` (K, 4, 4), of log-likelihood ``loglik``, with one object moved to each of ``starts`` (object,
    pose (4, 4)) and settled alone, the others kept, within ``max_shift_m`` and ``max_turn_deg`` of ``region``
    (default: each start), a search giving up as ``search`` says below ``give_up_below``; every search in lockstep
    (``run``) -> (each start's (scene, log-likelihood, scenes scored), object -> its best settled scene and
    log-likelihood where that gains more than TURN_MARGIN over ``loglik``)."""
    searches = []
    for k, pose in starts:
        start = scene.copy()
        start[k] = pose
        searches.append(search(start, step_m=SETTLE_STEP, step_deg=SETTLE_DEGREES, max_shift_m=max_shift_m,
                               max_turn_deg=max_turn_deg, objects=[k], region=region, give_up_below=give_up_below))
    found = run(searches, score)
    best: dict[int, tuple[np.ndarray, float]] = {}
    for (k, _), (T, ll, _) in zip(starts, found):
        if ll > loglik + TURN_MARGIN and (k not in best or ll > best[k][1]):
            best[k] = (T, ll)
    return found, best


def keep_held(scene: np.ndarray, loglik: float, best: dict[int, tuple[np.ndarray, float]], score: Score,
              rest: Rest, max_shift_m: float, max_turn_deg: float
              ) -> tuple[dict[int, float], tuple[np.ndarray, float], int]:
    """``scene`` (K, 4, 4), of log-likelihood ``loglik``, with those objects of ``best`` (object -> a scene where
    only it changed, and that scene's log-likelihood, which beats ``loglik``) that physics, resting their scenes
    (``rest``), keeps within ``max_shift_m`` and ``max_turn_deg`` of where they were fitted, as ``adopt`` takes them
    -> (object -> its new pose's log-likelihood alone, for those kept; (the scene, its log-likelihood); scenes
    scored)."""
    if not best:
        return {}, (scene, loglik), 0
    changed = list(best)
    rested = rest(np.stack([best[k][0] for k in changed]))
    held = [k for i, k in enumerate(changed)
            if within(rested[i, k], best[k][0][k], max_shift_m, np.radians(max_turn_deg))]
    if not held:
        return {}, (scene, loglik), 0
    return adopt(scene, {k: best[k] for k in held}, score)


def adopt(scene: np.ndarray, better: dict[int, tuple[np.ndarray, float]], score: Score
          ) -> tuple[dict[int, float], tuple[np.ndarray, float], int]:
    """``scene`` (K, 4, 4) with the objects of ``better`` (object -> a scene (K, 4, 4) where only that object
    changed, and its log-likelihood; each already beats ``scene`` clearly and physics holds it) in their new poses:
    the best one alone, or all of them together when that scene scores at least as well -> (object -> the
    log-likelihood of its new pose alone, for those kept; (the scene, its log-likelihood); scenes scored)."""
    first = max(better, key=lambda k: better[k][1])
    kept, result, scored = {first: better[first][1]}, better[first][:2], 0
    if len(better) > 1:
        together = scene.copy()
        for k in better:
            together[k] = better[k][0][k]
        together_ll = float(score(together[None])[0])
        scored += 1
        if together_ll >= better[first][1]:
            kept, result = {k: better[k][1] for k in better}, (together, together_ll)
    return kept, result, scored
