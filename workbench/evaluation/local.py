"""Evaluation in this process: ``LocalEvaluator`` with its own physics client and renderer, and
``ChunkedEvaluator``, which evaluates a batch in the parts a pool would split it into, one after another."""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from workbench.evaluation.base import Done, Evaluation, admissible, check_sink, run_here, split_batch
from workbench.geometry import check_rigid
from workbench.physics import STATUS_AS_GIVEN, STATUS_OUTSIDE, STATUS_REST, STATUS_STEP_CAP, make_projector
from workbench.problem.problem import Problem
from workbench.render.depth import DepthRenderer
from workbench.render.likelihood import pixel_loglik
from workbench.render.shared import draw_shared, drawn_loglik


def prepare_meshes(problem: Problem) -> None:
    """Choose every model's collision shape and render mesh now, in this process, saying so when that takes long
    (``meshes.heavy.announced``): a pool's workers then read them from the cache instead of each computing the same, and
    so do other processes preparing the same mesh meanwhile (Ray tasks, concurrent runs), which wait their turn
    (``meshes.heavy.one_at_a_time``)."""
    from workbench.meshes.heavy import announced, faces_text, mesh_key, one_at_a_time
    from workbench.physics.projector import collision_shapes
    from workbench.render.depth import default_cache_dir, render_mesh

    for model in problem.models:
        name = model.source.name if model.source is not None else model.name
        # One process at a time per mesh (its waiting announced as the work), the others then read the cache.
        with announced(f"simplifying {name} ({faces_text(len(model.mesh.faces))} faces) for collision and "
                       "rendering, once"), one_at_a_time(mesh_key(model.mesh), default_cache_dir().parent / "locks"):
            collision_shapes([model], problem.config.physics)
            render_mesh(model.mesh, problem.config.render.max_depth_error)


class LocalEvaluator:
    """Evaluates in this process with its own physics client and renderer."""

    def __init__(self, problem: Problem):
        self.problem = problem
        prepare_meshes(problem)
        self.projector = make_projector(problem.models, problem.table, problem.config.physics)
        self.renderer = DepthRenderer(
            problem.render_camera, [m.mesh for m in problem.models], problem.config.render
        )

    def evaluate(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Evaluation:
        hypotheses = check_rigid(hypotheses, "hypotheses")  # physics would turn a reflection into another pose
        t0 = time.perf_counter()
        sink = check_sink(sink, len(hypotheses))
        if project:
            projected, status, _ = self.projector.project_batch(hypotheses, sink)
        else:
            projected, status = hypotheses.copy(), np.full(len(hypotheses), STATUS_AS_GIVEN, np.int8)
        t1 = time.perf_counter()
        ok = (status == STATUS_REST) | (status == STATUS_STEP_CAP) | (status == STATUS_AS_GIVEN)
        outside = ok & ~admissible(projected, self.problem)
        status[outside] = STATUS_OUTSIDE
        ok &= ~outside
        loglik, floor_gain = np.full(len(hypotheses), -np.inf), np.zeros(len(hypotheses))
        drawn = draw_shared(self.renderer, projected[ok]) if ok.any() else None
        t2 = time.perf_counter()
        if drawn is not None:
            loglik[ok], floor_gain[ok] = drawn_loglik(drawn, self.problem.observed, self.problem.background,
                                      self.problem.config.likelihood, self.problem.clutter)
        t3 = time.perf_counter()
        return Evaluation(projected, loglik, status, floor_gain,
                          {"projection": t1 - t0, "render": t2 - t1, "likelihood": t3 - t2})

    def submit(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Done:
        return Done(self.evaluate(hypotheses, sink, project))

    def map(self, fn: Callable, calls: list[tuple]) -> list:
        return run_here(self.problem)(fn, calls)

    def retarget(self, problem: Problem) -> None:
        """Evaluate ``problem`` from now on (a sequence's next frame), as ``PoolEvaluator.retarget``."""
        self.close()
        LocalEvaluator.__init__(self, problem)

    def explain(self, T_world_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For display: one scene (K, 4, 4) as given (no projection) -> (rendered depth (h, w), per-pixel
        log-likelihood (h, w)) on the problem's grid."""
        rendered = self.renderer.render(T_world_obj[None])
        pixels = pixel_loglik(self.problem.observed, self.problem.background, rendered, self.problem.config.likelihood,
                              self.problem.clutter)
        return rendered[0], pixels[0]

    def close(self) -> None:
        self.projector.close()
        self.renderer.close()


class ChunkedEvaluator(LocalEvaluator):
    """Evaluates in this process, a batch split into ``chunks`` contiguous parts evaluated one after another: the
    same parts as a ``PoolEvaluator`` of ``chunks`` workers, each rendered from the framebuffer's first tile as a
    worker renders it, so results are bit-identical to that pool's on one CPU. Frames run as Ray tasks use it, so
    that a frame's result does not depend on the engine."""

    def __init__(self, problem: Problem, chunks: int):
        if chunks < 1:
            raise ValueError(f"chunks must be >= 1, got {chunks}")
        super().__init__(problem)
        self.chunks = chunks

    def evaluate(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Evaluation:
        return Evaluation.concatenate([LocalEvaluator.evaluate(self, h, s, project)
                                       for h, s in split_batch(hypotheses, self.chunks, sink)])
