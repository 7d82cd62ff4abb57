"""The engine's evaluators: the pool that scores each iteration's particles, and an in-process ``LocalEvaluator`` for
the single scenes the display and the labelling render (one particle's per-pixel likelihood, the labelled scene).

Both hold the problem they were made for: a new frame or likelihood closes them (``use``), and the pool is made
again on demand; another frame of a sequence is given to the running pool instead (``retarget``). A dead
evaluation worker surfaces as ``WorkerCrashed`` (or one of ``CRASH_ERRORS``): ``restart`` replaces the pool and the
server is told (``protocol.Workers``).
"""

from __future__ import annotations

import logging

import numpy as np

from workbench.app import protocol as p

log = logging.getLogger(__name__)

CRASH_ERRORS = (EOFError, BrokenPipeError, ConnectionError)


class Evaluators:
    def __init__(self, results, workers: int, ray=None):
        self.results = results
        self.workers = workers
        self.ray = ray  # a evaluation.ray.RayConfig: evaluate on Ray actors; None: here or on local processes
        self.problem = None
        self.pool = None
        self.explainer = None  # a LocalEvaluator in this process, for one particle's per-pixel likelihood

    def use(self, problem) -> None:
        """Evaluate ``problem`` from now on; the evaluators of the old one are closed (their workers hold it)."""
        self.close()
        self.problem = problem

    def retarget(self, problem):
        """-> the pool, evaluating ``problem`` from now on (another frame of a sequence): its running workers are
        given the new problem instead of being started again (a pool that cannot take one, Ray's actors, is made
        anew). The in-process explainer, made for the old problem, goes."""
        if self.pool is None or not hasattr(self.pool, "retarget"):
            self.use(problem)
            return self.evaluator()
        if self.explainer is not None and self.explainer is not self.pool:
            self.explainer.close()
        self.explainer = None
        self.pool.retarget(problem)
        self.problem = problem
        return self.pool

    def evaluating(self, problem):
        """-> the pool, evaluating ``problem`` (retargeted where it evaluates another frame's)."""
        return self.retarget(problem) if self.problem is not problem else self.evaluator()

    def evaluator(self):
        """The pool, made (and announced to the server) if there is none."""
        if self.pool is None:
            self.pool = self.make()
        return self.pool

    def make(self, crash: BaseException | None = None):
        from workbench.evaluation import make_evaluator

        evaluator = make_evaluator(self.problem, self.workers, self.ray)
        # The pids serve the status line and the crash tests; a LocalEvaluator has none.
        pids = getattr(evaluator, "pids", [])
        reason = "" if crash is None else f"{type(crash).__name__}: {crash}"
        self.results.put(p.Workers(pids, crash is not None, reason))
        return evaluator

    def close(self) -> None:
        for ev in {id(e): e for e in (self.pool, self.explainer) if e is not None}.values():
            try:
                ev.close()
            except Exception:  # a crashed pool may fail to close cleanly; it is being replaced anyway
                log.exception("closing an evaluator")
        self.pool = self.explainer = None

    def restart(self, err: BaseException):
        """-> a fresh pool in place of the one a worker of which died with ``err``."""
        log.warning("an evaluation worker died (%s: %s); starting a fresh pool and retrying the iteration",
                    type(err).__name__, err)
        try:
            self.pool.close()
        except Exception:
            log.exception("closing a crashed pool")
        if self.explainer is self.pool:
            self.explainer = None
        self.pool = self.make(crash=err)
        return self.pool

    def local(self):
        """A LocalEvaluator of this process (the pool itself when it is one) for display and labelling."""
        from workbench.evaluation import LocalEvaluator

        if self.explainer is None:
            self.explainer = self.pool if isinstance(self.pool, LocalEvaluator) else LocalEvaluator(self.problem)
        return self.explainer

    def explain(self, scene: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One scene (K, 4, 4) as given -> (per-pixel log-likelihood, observed - predicted depth (NaN: either
        missing)) on the problem grid, from one render."""
        from workbench.render.likelihood import predicted_depth

        rendered, pixels = self.local().explain(scene)
        predicted = predicted_depth(rendered[None], self.problem.background)[0]
        observed = self.problem.observed
        residual = np.where((observed > 0) & (predicted > 0), observed - predicted, np.nan).astype(np.float32)
        return pixels, residual

    def describe(self) -> str:
        """Where the evaluation runs, as a saved session's note says it."""
        if self.ray is not None:
            return f"{self.workers} Ray actors"
        return "in-process" if self.workers <= 1 else f"{self.workers} workers"
