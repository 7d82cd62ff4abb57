"""Particle evaluation behind one small interface (``base.Evaluator``): a batch of hypotheses in, projected poses and
log-likelihoods out. Where the work runs is the evaluator's business, one module per backend:

- ``local``: this process (``LocalEvaluator``; ``ChunkedEvaluator``, a pool's split evaluated in turn);
- ``pool``: spawned worker processes on this machine (``PoolEvaluator``);
- ``ray``: Ray actors on a cluster (``RayEvaluator``, the optional extra ``workbench[ray]``).

``make_evaluator`` picks one. The Ray backend is imported only when it is picked, so that everything else works
without Ray; the local ones need nothing beyond the core dependencies and are re-exported here.
"""

from __future__ import annotations

from workbench.evaluation.base import (
    STAGES,
    Done,
    Evaluation,
    Evaluator,
    Pending,
    WorkerCrashed,
    admissible,
    check_sink,
    hidden_behind_region,
    in_region,
    in_view,
    joined,
    run_here,
    split_batch,
    split_calls,
)
from workbench.evaluation.local import ChunkedEvaluator, LocalEvaluator
from workbench.evaluation.pool import PoolEvaluator
from workbench.problem.problem import Problem

__all__ = [
    "STAGES", "ChunkedEvaluator", "Done", "Evaluation", "Evaluator", "LocalEvaluator", "Pending", "PoolEvaluator",
    "WorkerCrashed", "admissible", "check_sink", "hidden_behind_region", "in_region", "in_view", "joined",
    "make_evaluator", "run_here", "split_batch", "split_calls",
]


def make_evaluator(problem: Problem, workers: int, ray=None, max_retries: int = 0) -> Evaluator:
    """A local evaluator for ``workers`` <= 1, else a process pool (whose dead workers are started again, their
    part of the batch retried, up to ``max_retries`` times per batch); with ``ray`` (an
    ``evaluation.ray.RayConfig``), ``workers`` Ray actors. Results are the same for the same ``workers`` whichever
    it is."""
    if ray is not None:
        from workbench.evaluation.ray import RayEvaluator  # Ray is an optional extra

        return RayEvaluator(problem, workers, ray)
    return LocalEvaluator(problem) if workers <= 1 else PoolEvaluator(problem, workers, max_retries)
