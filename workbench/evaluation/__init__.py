"""Particle evaluation behind one small interface: a batch of hypotheses in, projected poses and log-likelihoods
out. The estimators see only ``Evaluator``; where the work runs (this process, a pool of local workers, or Ray actors
on a cluster: ``workbench.evaluation.ray.RayEvaluator``) is the evaluator's business. ``submit`` hands a batch over and
returns at once where the work runs elsewhere, so that the caller can prepare the next batch meanwhile;
``evaluate`` is ``submit(...).result()``. ``map`` runs the search's own pure work (candidate fits) on the same
workers, so that they do not wait while the main process fits.

Each evaluation is independent of every other (physics rebuilds its world per particle), so splitting a batch
across workers never changes a result.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from workbench.checks import check_rigid
from workbench.errors import InputError
from workbench.likelihood import pixel_loglik, predicted_depth, scene_loglik
from workbench.physics import STATUS_AS_GIVEN, STATUS_OUTSIDE, STATUS_REST, STATUS_STEP_CAP, PhysicsProjector
from workbench.problem import Problem
from workbench.scene import Table
from workbench.render import DepthRenderer

STAGES = ("projection", "render", "likelihood")


@dataclass
class Evaluation:
    """Results for B hypotheses: ``projected`` (B, K, 4, 4) resting poses, ``loglik`` (B,) (-inf where physics
    failed), ``status`` (B,) physics status codes, ``timings`` seconds spent per stage (summed over workers)."""

    projected: np.ndarray
    loglik: np.ndarray
    status: np.ndarray
    timings: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))

    @staticmethod
    def concatenate(parts: list["Evaluation"]) -> "Evaluation":
        return Evaluation(
            projected=np.concatenate([p.projected for p in parts]),
            loglik=np.concatenate([p.loglik for p in parts]),
            status=np.concatenate([p.status for p in parts]),
            timings={s: sum(p.timings[s] for p in parts) for s in STAGES},
        )

    @staticmethod
    def interleave(first: np.ndarray, a: "Evaluation", b: "Evaluation") -> "Evaluation":
        """The evaluation of a batch whose hypotheses where ``first`` (B,) is true were evaluated as ``a`` and the
        others as ``b``, both in order."""
        projected = np.empty((len(first), *a.projected.shape[1:]))
        loglik, status = np.empty(len(first)), np.empty(len(first), dtype=a.status.dtype)
        for part, where in ((a, first), (b, ~first)):
            projected[where], loglik[where], status[where] = part.projected, part.loglik, part.status
        return Evaluation(projected, loglik, status, {s: a.timings[s] + b.timings[s] for s in STAGES})


class Pending(Protocol):
    def result(self) -> Evaluation:
        """The submitted batch's evaluation, waiting for it if need be."""
        ...


@dataclass
class Done:
    """A batch evaluated at submission (evaluators that work in the caller's process)."""

    evaluation: Evaluation

    def result(self) -> Evaluation:
        return self.evaluation


class Evaluator(Protocol):
    def evaluate(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Evaluation:
        """(B, K, 4, 4) hypotheses in the table frame -> their evaluation. ``sink`` (B,) m, default 0: how far
        below the fitted table plane each hypothesis's objects rest (``PhysicsProjector.project``); the observed
        table is drawn where it was fitted either way. ``project=False`` scores the hypotheses as given, without
        physics (``inference.settle``): ``projected`` is then the hypotheses, with status ``STATUS_AS_GIVEN``."""
        ...

    def submit(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Pending:
        """``evaluate``, but returning as soon as the batch is handed over; results are the same. Batches are
        evaluated in the order submitted."""
        ...

    def map(self, fn: Callable, calls: list[tuple]) -> list:
        """``[fn(problem, *args) for args in calls]``, run where the evaluations run: the search's own pure work
        (candidate fits), which would otherwise keep one core busy while the workers wait. ``fn`` must be a
        module-level function (it is pickled by name); the results are the same as in this process."""
        ...

    def close(self) -> None: ...


def in_region(T_world_obj: np.ndarray, table: Table, margin: float) -> np.ndarray:
    """Whether every object's origin (B, K, 4, 4 table frame) lies within ``margin`` (m) of the table's object
    region -> (B,) bool."""
    xy = T_world_obj[:, :, :2, 3]
    lo, hi = np.asarray(table.region_min) - margin, np.asarray(table.region_max) + margin
    return np.all((xy >= lo) & (xy <= hi), axis=(1, 2))


class LocalEvaluator:
    """Evaluates in this process with its own physics client and renderer."""

    def __init__(self, problem: Problem):
        self.problem = problem
        self.projector = PhysicsProjector(problem.models, problem.table, problem.config.physics)
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
        outside = ok & ~in_region(projected, self.problem.table, self.problem.config.region_margin)
        status[outside] = STATUS_OUTSIDE
        ok &= ~outside
        loglik = np.full(len(hypotheses), -np.inf)
        rendered = self.renderer.render(projected[ok]) if ok.any() else None
        t2 = time.perf_counter()
        if rendered is not None:
            loglik[ok] = scene_loglik(
                self.problem.observed, self.problem.background, rendered, self.problem.config.likelihood
            )
        t3 = time.perf_counter()
        return Evaluation(projected, loglik, status, {"projection": t1 - t0, "render": t2 - t1, "likelihood": t3 - t2})

    def submit(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Done:
        return Done(self.evaluate(hypotheses, sink, project))

    def map(self, fn: Callable, calls: list[tuple]) -> list:
        return run_here(self.problem)(fn, calls)

    def explain(self, T_world_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For display: one scene (K, 4, 4) as given (no projection) -> (rendered depth (h, w), per-pixel
        log-likelihood (h, w)) on the problem's grid."""
        rendered = self.renderer.render(T_world_obj[None])
        pixels = pixel_loglik(
            self.problem.observed, predicted_depth(rendered, self.problem.background), self.problem.config.likelihood
        )
        return rendered[0], pixels[0]

    def close(self) -> None:
        self.projector.close()
        self.renderer.close()


def _worker(problem: Problem, conn) -> None:
    # One llvmpipe thread per worker: the pool already keeps every core busy, extra render threads only contend.
    os.environ.setdefault("LP_NUM_THREADS", "1")
    evaluator = LocalEvaluator(problem)
    try:
        while True:
            message = conn.recv()
            if message is None:
                break
            kind, *args = message
            conn.send(evaluator.evaluate(*args) if kind == "evaluate" else evaluator.map(*args))
    except (EOFError, KeyboardInterrupt):
        pass
    finally:
        evaluator.close()
        conn.close()


def check_sink(sink: np.ndarray | None, n: int) -> np.ndarray:
    """The per-hypothesis sink (n,) m, zeros if None; a clear error for a wrong shape or a non-finite value."""
    if sink is None:
        return np.zeros(n)
    sink = np.asarray(sink, dtype=np.float64)
    if sink.shape != (n,) or not np.all(np.isfinite(sink)):
        raise InputError("sink", f"expected {n} finite values in metres, got shape {sink.shape}")
    return sink


def split_batch(hypotheses: np.ndarray, parts: int, sink: np.ndarray | None = None
                ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The checked batch (N, K, 4, 4) and its sink (N,) in up to ``parts`` contiguous non-empty chunks, in order:
    chunk i goes to worker i. Every evaluator that splits a batch splits it this way, so results do not depend on
    which one ran. Checked here, not only in the workers: a refused batch must not look like a crashed worker."""
    hypotheses = check_rigid(hypotheses, "hypotheses")
    sink = check_sink(sink, len(hypotheses))
    return [(h, s) for h, s in zip(np.array_split(hypotheses, parts), np.array_split(sink, parts)) if len(h)]


def run_here(problem: Problem) -> Callable[[Callable, list[tuple]], list]:
    """``Evaluator.map`` done in this process: ``run(fn, calls)`` -> ``[fn(problem, *args) for args in calls]``."""
    return lambda fn, calls: [fn(problem, *args) for args in calls]


def split_calls(calls: list[tuple], parts: int) -> list[list[tuple]]:
    """``calls`` in up to ``parts`` contiguous non-empty chunks, in order, as ``split_batch`` splits a batch."""
    return [[calls[i] for i in idx] for idx in np.array_split(np.arange(len(calls)), parts) if len(idx)]


def joined(parts: list[list]) -> list:
    """The results of ``split_calls``' chunks, back in one list in call order."""
    return [r for part in parts for r in part]


class WorkerCrashed(RuntimeError):
    """A worker process died mid-evaluation; the pool must be rebuilt."""


class _PoolPending:
    """A job submitted to a ``PoolEvaluator``: one message per worker (a chunk of a batch to evaluate, or of calls
    to map), how the workers' replies combine, and the combined result once received."""

    def __init__(self, pool: "PoolEvaluator", messages: list[tuple], combine: Callable):
        self.pool, self.messages, self.combine = pool, messages, combine
        self.done, self.value = False, None

    def result(self):
        while not self.done:
            self.pool._advance()
        return self.value


class PoolEvaluator:
    """Splits each batch into contiguous chunks over ``workers`` spawned processes, each holding its own physics
    client and renderer, created once. ``spawn`` because forking after any OpenGL context exists hangs the child.

    One job (a batch, or calls to ``map``) is with the workers at a time; later ones wait here and go out as soon as
    the one before is received. (Sending a second job while a worker is still sending back the first can fill both
    directions of its pipe and hang both sides.)"""

    def __init__(self, problem: Problem, workers: int = 2):
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        ctx = mp.get_context("spawn")
        self._conns = []
        self._procs = []
        for _ in range(workers):
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=_worker, args=(problem, child), daemon=True)
            proc.start()
            child.close()
            self._conns.append(parent)
            self._procs.append(proc)
        self._in_flight: _PoolPending | None = None
        self._waiting: deque[_PoolPending] = deque()

    @property
    def pids(self) -> list[int]:
        """Process ids of the workers (for monitoring and crash tests)."""
        return [proc.pid for proc in self._procs]

    def evaluate(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Evaluation:
        return self.submit(hypotheses, sink, project).result()

    def submit(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> _PoolPending:
        chunks = split_batch(hypotheses, len(self._conns), sink)
        return self._queue(_PoolPending(self, [("evaluate", h, s, project) for h, s in chunks],
                                        Evaluation.concatenate))

    def map(self, fn: Callable, calls: list[tuple]) -> list:
        """The calls split over the workers as a batch is; queued behind the batches submitted before."""
        chunks = split_calls(list(calls), len(self._conns))
        if not chunks:
            return []
        return self._queue(_PoolPending(self, [("map", fn, chunk) for chunk in chunks], joined)).result()

    def _queue(self, pending: _PoolPending) -> _PoolPending:
        self._waiting.append(pending)
        if self._in_flight is None:
            self._send_next()
        return pending

    def _send_next(self) -> None:
        pending = self._in_flight = self._waiting.popleft()
        try:
            for conn, message in zip(self._conns, pending.messages):
                conn.send(message)
        except (ConnectionError, OSError) as err:
            self._fail(err)

    def _advance(self) -> None:
        """Receive the job in flight, then send the next waiting one."""
        pending = self._in_flight
        try:
            pending.value = pending.combine([conn.recv() for conn in self._conns[: len(pending.messages)]])
        except (EOFError, ConnectionError, OSError) as err:
            self._fail(err)
        pending.done = True
        self._in_flight = None
        if self._waiting:
            self._send_next()

    def _fail(self, err: Exception):
        # The pool is broken: every submitted batch is lost with it (the caller rebuilds the pool).
        self._in_flight, self._waiting = None, deque()
        raise WorkerCrashed(f"an evaluation worker died: {err!r}") from err

    def close(self) -> None:
        for conn in self._conns:
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
        for proc in self._procs:
            proc.join(timeout=5)
            if proc.is_alive():
                proc.kill()
        for conn in self._conns:
            conn.close()


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


def make_evaluator(problem: Problem, workers: int, ray=None) -> Evaluator:
    """A local evaluator for ``workers`` <= 1, else a process pool; with ``ray`` (an ``evaluation.ray.RayConfig``),
    ``workers`` Ray actors. Results are the same for the same ``workers`` whichever it is."""
    if ray is not None:
        from workbench.evaluation.ray import RayEvaluator  # Ray is an optional extra

        return RayEvaluator(problem, workers, ray)
    return LocalEvaluator(problem) if workers <= 1 else PoolEvaluator(problem, workers)
