"""Settle: the last millimetres of a scene, fitted to the observed depth without physics.

Physics projection keeps a scene plausible, but our models of the world are not the world: on the real YCB-Video
frames the annotated objects rest 4-12 mm below the plane fitted to the table's depth, and projecting the true
scene moves the banana by 6 mm and turns it by 5 degrees (docs/benchmarks.md). The search's estimate is such a
projected scene, a few millimetres and degrees from what the depth shows. Settling fits it to the depth with a
pattern search on the likelihood of the scene as given, each object kept within a small trust region around its
pose in the estimate, so the physics that chose the scene (support, stacking, what hides what) still holds to
within that region. An object the camera does not see gains nothing from any move and stays where physics put it.
``half_turns`` gives the turns that the depth can hardly tell apart (a can upside down, a bottle facing the other
way): the search compares them only after physics, where the same few millimetres of mismatch decide them, so the
estimator settles them too and keeps a turn that wins clearly (``Estimator._turn_over``).

``pattern_search`` is also how a ground-truth label is fitted to the depth (``labels.fit_label``, no region).
"""

from __future__ import annotations

import itertools
from typing import Callable

import numpy as np

from workbench.geometry import euler_to_matrix, rotation_angle

Score = Callable[[np.ndarray], np.ndarray]  # scenes (B, K, 4, 4) as given -> log-likelihoods (B,)


def single_moves(T: np.ndarray, step_m: float, step_rad: float) -> np.ndarray:
    """Every single-coordinate move of one object: +-step along the table's x, y, z, and +-step rotations about
    table axes through the object's origin (as ``inference.gaussian``). (K, 4, 4) -> (K, 12, K, 4, 4)."""
    K = len(T)
    out = np.broadcast_to(T, (K, 12, K, 4, 4)).copy()
    for k in range(K):
        for j, (axis, sign) in enumerate(itertools.product(range(3), (1.0, -1.0))):
            out[k, j, k, axis, 3] += sign * step_m
            out[k, 6 + j, k, :3, :3] = euler_to_matrix(np.eye(3)[axis] * sign * step_rad) @ T[k, :3, :3]
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
    R = T[:3, :3]
    c = R @ centre + T[:3, 3]
    axes = R[:, np.argsort(np.abs(R[2]))[:2]].T.copy()  # the two object axes nearest the table plane
    axes[:, 2] = 0.0
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    out = np.repeat(T[None], 3, axis=0)
    for i, axis in enumerate([np.array([0.0, 0.0, 1.0]), *axes]):
        H = 2.0 * np.outer(axis, axis) - np.eye(3)  # the half turn about a unit axis
        out[i, :3, :3] = H @ R
        out[i, :3, 3] = H @ (T[:3, 3] - c) + c
    return out


def pattern_search(T: np.ndarray, score: Score, step_m: float = 0.01, step_deg: float = 4.0,
                   min_step_m: float = 5e-4, max_rounds: int = 80, max_shift_m: float = np.inf,
                   max_turn_deg: float = np.inf, objects: list[int] | None = None) -> tuple[np.ndarray, float, int]:
    """Fit a scene (K, 4, 4) to the depth by ``score`` (the likelihood of scenes as given) -> (the fitted scene,
    its log-likelihood, how many scenes were scored).

    Each round tries every object's +-step moves along and about the table axes (``single_moves``), keeps the best
    move of each object when together they beat the best single move (else that one), and halves the steps when
    nothing improves, down to ``min_step_m`` (angles shrink alike). A move that takes an object more than
    ``max_shift_m`` or ``max_turn_deg`` from its pose in ``T`` is not tried; only the ``objects`` listed move
    (default: all). Local: it refines a scene within about two steps of the optimum, it does not find one."""
    origin = np.array(T, dtype=np.float64)
    T, K = origin.copy(), len(origin)
    best, scored = float(score(T[None])[0]), 1
    max_turn = np.radians(max_turn_deg)
    scale = 1.0
    for _ in range(max_rounds):
        if step_m * scale < min_step_m:
            break
        moves = single_moves(T, step_m * scale, np.radians(step_deg) * scale)  # (K, 12, K, 4, 4)
        allowed = within(moves[np.arange(K), :, np.arange(K)], origin[:, None], max_shift_m, max_turn)  # (K, 12)
        if objects is not None:
            allowed[np.setdiff1d(np.arange(K), objects)] = False
        ll = np.full((K, 12), -np.inf)
        if allowed.any():
            ll[allowed] = score(moves[allowed])
            scored += int(allowed.sum())
        own = ll.argmax(axis=1)  # each object's best move
        improving = np.flatnonzero(ll[np.arange(K), own] > best)
        k, j = np.unravel_index(np.argmax(ll), ll.shape)
        if len(improving) > 1:  # with one, the combination is that move: no need to score it again
            combined = T.copy()
            for i in improving:
                combined[i] = moves[i, own[i], i]
            combined_ll = float(score(combined[None])[0])
            scored += 1
            if combined_ll >= ll[k, j]:
                T, best = combined, combined_ll
                continue
        if ll[k, j] > best:
            T, best = moves[k, j], float(ll[k, j])
        else:
            scale /= 2.0
    return T, best, scored
