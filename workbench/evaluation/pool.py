"""Evaluation over a pool of spawned worker processes on this machine (``PoolEvaluator``), each with its own
``LocalEvaluator``."""

from __future__ import annotations

import multiprocessing as mp
import os
from collections import deque
from typing import Callable

import numpy as np

from workbench.evaluation.base import Evaluation, WorkerCrashed, joined, split_batch, split_calls
from workbench.evaluation.local import LocalEvaluator
from workbench.problem import Problem


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
