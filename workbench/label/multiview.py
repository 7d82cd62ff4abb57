"""Fitting a sequence's still labels to the depth of many frames at once.

One view leaves some things open (a mug's hidden handle, a can's turn); the frames that show them decide them. A
scene's multi-view log-likelihood is the sum of its log-likelihoods in a spread of the sequence's frames, each
rendered from that frame's camera in the sequence's world frame (``MultiView.logliks``). On it:
- ``choose``: each object's pose among candidates (the poses the frames' own estimates gave it), the others held;
- ``fit``: ``settle.pattern_search`` from there, every object at once, no physics while fitting;
then the caller snaps the scene with physics (``frame.snap_to_plausible``), as one frame's *Fit to depth* does.

Summing frames counts consecutive views as independent evidence, which they are not (the sensor's error repeats);
the sum only ranks poses here, it is not a posterior.
"""

from __future__ import annotations

import numpy as np

from workbench.inference.answer.settle import pattern_search
from workbench.problem.problem import Problem
from workbench.render.depth import DepthRenderer
from workbench.render.likelihood import scene_loglik
from workbench.score.metrics import is_right


def spread(frames: list[int], n: int) -> list[int]:
    """``n`` frames of ``frames`` (sorted image ids) evenly spread, the first and last included (all when fewer)."""
    if n >= len(frames):
        return list(frames)
    at = np.unique(np.round(np.linspace(0, len(frames) - 1, max(n, 2))).astype(int))
    return [frames[i] for i in at]


class MultiView:
    """The multi-view log-likelihood over ``problems`` (one per frame, all in the sequence's world frame), with
    ``present`` (F, K) bool: which labels each frame draws (an object taken out is not drawn after its last
    frame). Holds a renderer per frame: ``close`` it."""

    def __init__(self, problems: list[Problem], present: np.ndarray):
        self.problems = problems
        self.present = np.asarray(present, dtype=bool)
        self.renderers = [DepthRenderer(p.render_camera, [m.mesh for m in p.models], p.config.render)
                          for p in problems]
        self.scored = 0

    def logliks(self, scenes: np.ndarray) -> np.ndarray:
        """Scenes (B, K, 4, 4), world frame -> (B,) the sum over frames of each scene's log-likelihood as given."""
        scenes = np.asarray(scenes, dtype=np.float64)
        total = np.zeros(len(scenes))
        for problem, renderer, drawn in zip(self.problems, self.renderers, self.present):
            rendered = renderer.render(scenes, drawn=np.repeat(drawn[None], len(scenes), axis=0))
            total += scene_loglik(problem.observed, problem.background, rendered, problem.config.likelihood,
                                  problem.clutter)
        self.scored += len(scenes)
        return total

    def close(self) -> None:
        for r in self.renderers:
            r.close()


def distinct(candidates: list[np.ndarray], symmetries: np.ndarray) -> list[np.ndarray]:
    """Candidate poses (each (4, 4)) without repeats: one kept of those within the benchmarks' "right" tolerances
    of each other (with the object's ``symmetries``)."""
    out: list[np.ndarray] = []
    for T in candidates:
        if not any(is_right(T, U, symmetries) for U in out):
            out.append(T)
    return out


def choose(view: MultiView, T: np.ndarray, candidates: list[list[np.ndarray]], symmetries: list[np.ndarray]
           ) -> np.ndarray:
    """Each object's pose among its ``candidates`` (per object a list of (4, 4)) by the multi-view log-likelihood,
    objects in turn, the others as chosen so far -> the scene (K, 4, 4)."""
    T = np.array(T, dtype=np.float64)
    for k, poses in enumerate(candidates):
        poses = distinct([T[k], *poses], symmetries[k])
        if len(poses) < 2:
            continue
        scenes = np.repeat(T[None], len(poses), axis=0)
        scenes[:, k] = poses
        T = scenes[int(np.argmax(view.logliks(scenes)))]
    return T


def fit(view: MultiView, T: np.ndarray, step_m: float = 0.005, step_deg: float = 2.0, min_step_m: float = 5e-4,
        max_rounds: int = 40, max_shift_m: float = np.inf, max_turn_deg: float = np.inf) -> np.ndarray:
    """``pattern_search`` of the scene (K, 4, 4) on the multi-view log-likelihood, each object within
    ``max_shift_m`` and ``max_turn_deg`` of where it starts -> the fitted scene. Steps start at half a frame's *Fit
    to depth*: the frames' estimates are already within a few millimetres."""
    fitted, _, _ = pattern_search(T, view.logliks, step_m, step_deg, min_step_m, max_rounds, max_shift_m,
                                  max_turn_deg)
    return fitted
