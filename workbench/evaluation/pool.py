"""Evaluation over a pool of spawned worker processes on this machine (``PoolEvaluator``), each with its own
``LocalEvaluator``."""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
from collections import deque
from dataclasses import replace
from typing import Callable

import numpy as np

from workbench.errors import InputError, is_whole_number
from workbench.evaluation.base import Evaluation, WorkerCrashed, joined, split_batch, split_calls
from workbench.evaluation.local import LocalEvaluator, prepare_meshes
from workbench.problem.problem import Problem

log = logging.getLogger(__name__)
# Memory one evaluation worker needs: docs/benchmarks.md's speed table measured 433 MB peak per worker (4 objects, 1444
# particles); the rest is headroom for larger meshes and the main process's share. It bounds ``--workers``.
WORKER_MEMORY_BYTES = 600 * 2**20
# A run's peak resident memory grows with its particles and the pixels each is rendered at: on the demo (2 objects,
# 160 x 120 renders, one iteration, one worker) 0.62 GB for 1000 particles and 2.46 GB for 8000, so ~14 bytes per
# particle and rendered pixel over ~0.4 GB. It bounds --particles before the run (``check_run_memory``).
RUN_BASE_BYTES = 400 * 2**20
BYTES_PER_PARTICLE_PIXEL = 14


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def available_memory() -> int | None:
    """Bytes of memory available to new processes (Linux MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def run_memory(particles: int, render_pixels: int) -> int:
    """Bytes a run of ``particles`` rendered at ``render_pixels`` pixels each is expected to hold at its peak."""
    return RUN_BASE_BYTES + particles * render_pixels * BYTES_PER_PARTICLE_PIXEL


def check_run_memory(particles: int, render_pixels: int, where: str = "--particles") -> None:
    """InputError naming ``where``, before the run, when ``run_memory`` exceeds the memory available here: such a
    run would swap for minutes and then be killed."""
    need, memory = run_memory(particles, render_pixels), available_memory()
    if memory is not None and need > memory:
        raise InputError(where, f"{particles} particles rendered at {render_pixels} pixels each would need about "
                                f"{need / 2**30:.1f} GiB (~{BYTES_PER_PARTICLE_PIXEL} bytes per particle and pixel, "
                                f"measured), and this machine has {memory / 2**30:.1f} GiB free: use fewer "
                                "particles or a smaller --max-render-pixels")


def max_workers() -> int:
    """The most evaluation workers worth starting here: one per usable core, and no more than the available
    memory holds at ``WORKER_MEMORY_BYTES`` each (at least 1)."""
    bound = usable_cores()
    memory = available_memory()
    if memory is not None:
        bound = min(bound, memory // WORKER_MEMORY_BYTES)
    return max(1, int(bound))


def check_workers(workers, where: str = "--workers") -> int:
    """``workers`` if 1 <= workers <= max_workers(), else InputError saying the bound and why."""
    bound = max_workers()
    if not is_whole_number(workers) or not 1 <= workers <= bound:
        memory = available_memory()
        free = "" if memory is None else f", {memory / 2**30:.1f} GiB free"
        raise InputError(where, f"evaluation workers must be a whole number from 1 to {bound} on this machine "
                                f"({usable_cores()} cores{free}, ~{WORKER_MEMORY_BYTES // 2**20} MB per worker), "
                                f"got {workers!r}")
    return int(workers)


def _worker(conn, factory: Callable[[Problem], object] | None = None) -> None:
    # One llvmpipe thread per worker: the pool already keeps every core busy, extra render threads only contend.
    os.environ.setdefault("LP_NUM_THREADS", "1")
    try:
        problem = conn.recv()  # the first message (``PoolEvaluator._hand_problem``)
    except (EOFError, KeyboardInterrupt, OSError):
        return
    if problem is None:  # closed before it had a problem (another worker died as it started)
        conn.close()
        return
    evaluator = (factory or LocalEvaluator)(problem)
    try:
        while True:
            message = conn.recv()
            if message is None:
                break
            kind, *args = message
            if kind in ("problem", "frame"):  # a sequence's next frame: a new evaluator here, no new process
                # "frame": the same objects, sent without their meshes; the ones this worker holds keep what
                # trimesh cached on them (masses, hulls), which would otherwise be computed again for every frame.
                problem = args[0] if kind == "problem" else replace(args[0], models=problem.models)
                evaluator.close()
                evaluator = (factory or LocalEvaluator)(problem)
                conn.send(None)
                continue
            conn.send(evaluator.evaluate(*args) if kind == "evaluate" else evaluator.map(*args))
    except (EOFError, KeyboardInterrupt, OSError):
        pass  # the main process is gone (killed, Ctrl-C, SIGTERM): nothing to send the answer to, and no traceback
    finally:
        evaluator.close()
        conn.close()


class _PoolPending:
    """A job submitted to a ``PoolEvaluator``: one message per worker (a chunk of a batch to evaluate, or of calls
    to map), how the workers' replies combine, and the combined result once received."""

    def __init__(self, pool: "PoolEvaluator", messages: list[tuple], combine: Callable):
        self.pool, self.messages, self.combine = pool, messages, combine
        self.done, self.value = False, None
        self.retries = 0  # workers restarted for this job

    def result(self):
        while not self.done:
            self.pool._advance()
        return self.value


class PoolEvaluator:
    """Splits each batch into contiguous chunks over ``workers`` spawned processes, each holding its own physics
    client and renderer, created once. ``spawn`` because forking after any OpenGL context exists hangs the child.

    One job (a batch, or calls to ``map``) is with the workers at a time; later ones wait here and go out as soon as
    the one before is received. (Sending a second job while a worker is still sending back the first can fill both
    directions of its pipe and hang both sides.)

    A worker that dies (killed, out of memory) is started again and sent its part of the job again, up to
    ``max_retries`` times per job, each time with one WARNING line; the job's result is the one an undisturbed pool
    gives (each evaluation is independent of every other). Past ``max_retries`` (default 0: the caller rebuilds the
    pool, as the app does) the job raises ``WorkerCrashed``. ``factory(problem)`` builds each worker's evaluator
    (default ``LocalEvaluator``; a module-level callable, pickled by name)."""

    def __init__(self, problem: Problem, workers: int = 2, max_retries: int = 0,
                 factory: Callable[[Problem], object] | None = None):
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self._problem, self._factory, self.max_retries = problem, factory, max_retries
        if factory is None:
            prepare_meshes(problem)  # once, here: the workers read the shapes and meshes from the cache
        self._ctx = mp.get_context("spawn")
        self._conns: list = [None] * workers
        self._procs: list = [None] * workers
        self._in_flight: _PoolPending | None = None
        self._waiting: deque[_PoolPending] = deque()
        for i in range(workers):  # all started before any is sent its problem: they import side by side
            self._start(i)
        try:
            for i in range(workers):
                self._hand_problem(i)
        except WorkerCrashed:
            self.close()  # the workers that did start: not left running without a pool
            raise

    def _start(self, i: int) -> None:
        parent, child = self._ctx.Pipe()
        proc = self._ctx.Process(target=_worker, args=(child, self._factory), daemon=True)
        proc.start()
        child.close()
        self._conns[i], self._procs[i] = parent, proc

    def _hand_problem(self, i: int) -> None:
        """Send worker ``i`` the problem, its first message. Over the worker's own pipe, not as the process's
        arguments: ``multiprocessing`` writes those to a pipe whose reading end it holds itself until the write
        ends, so a problem larger than the pipe's buffer, sent to a worker that dies as it starts, blocks the
        caller for ever. Here that worker's death closes the pipe, and the caller is told."""
        try:
            self._conns[i].send(self._problem)
        except (ConnectionError, OSError) as err:
            proc = self._procs[i]
            proc.join(timeout=5)
            raise WorkerCrashed(
                f"evaluation worker {i + 1} exited as it started (exit code {proc.exitcode}; its error is above). A "
                "script that evaluates in a pool must start it under `if __name__ == \"__main__\":`, since each "
                "worker imports the script again (multiprocessing's spawn)") from err

    def _restart(self, i: int, pending: _PoolPending, err: Exception) -> None:
        """Worker ``i`` died during ``pending``: start it again (WorkerCrashed past ``max_retries``)."""
        proc = self._procs[i]
        proc.join(timeout=1)
        if proc.is_alive():
            proc.kill()
            proc.join(timeout=5)
        self._conns[i].close()
        pending.retries += 1
        if pending.retries > self.max_retries:
            self._fail(err, f" ({pending.retries - 1} restart(s) allowed by --max-retries)"
                       if self.max_retries else "")
        how = f"exit code {proc.exitcode}" if proc.exitcode is not None else type(err).__name__
        log.warning("evaluation worker %d (pid %s) died (%s); started it again and retried its part of the batch "
                    "(retry %d of %d)", i + 1, proc.pid, how, pending.retries, self.max_retries)
        self._start(i)
        try:
            self._hand_problem(i)
        except WorkerCrashed as again:
            self._fail(again)

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
        """The calls dealt out to the workers (``split_calls``); queued behind the batches submitted before."""
        chunks = split_calls(list(calls), len(self._conns))
        if not chunks:
            return []
        return self._queue(_PoolPending(self, [("map", fn, chunk) for chunk in chunks], joined)).result()

    def retarget(self, problem: Problem) -> None:
        """Evaluate ``problem`` from now on (a sequence's next frame): each worker builds its evaluator anew, in the
        process it already runs, which saves starting the processes and importing the libraries again. Queued, not
        waited for: the caller prepares the frame's search meanwhile, and the batches it submits next are evaluated
        after it (a worker that dies building it is restarted, or raises ``WorkerCrashed``, at their result)."""
        same = len(problem.models) == len(self._problem.models) and all(
            a is b for a, b in zip(problem.models, self._problem.models))
        self._problem = problem  # a worker started again from now on gets the new problem
        if same:  # the workers keep their models (``_worker``); the shapes and meshes are prepared already
            message = ("frame", replace(problem, models=[]))
        else:
            message = ("problem", problem)
            if self._factory is None:
                prepare_meshes(problem)
        self._queue(_PoolPending(self, [message] * len(self._conns), lambda replies: None))

    def _queue(self, pending: _PoolPending) -> _PoolPending:
        self._waiting.append(pending)
        if self._in_flight is None:
            self._send_next()
        return pending

    def _send_next(self) -> None:
        pending = self._in_flight = self._waiting.popleft()
        for i, message in enumerate(pending.messages):
            self._send(i, message, pending)

    def _send(self, i: int, message: tuple, pending: _PoolPending) -> None:
        while True:
            try:
                self._conns[i].send(message)
                return
            except (ConnectionError, OSError) as err:
                self._restart(i, pending, err)

    def _receive(self, i: int, pending: _PoolPending):
        while True:
            try:
                return self._conns[i].recv()
            except (EOFError, ConnectionError, OSError) as err:
                self._restart(i, pending, err)
                self._send(i, pending.messages[i], pending)

    def _advance(self) -> None:
        """Receive the job in flight, then send the next waiting one."""
        pending = self._in_flight
        pending.value = pending.combine([self._receive(i, pending) for i in range(len(pending.messages))])
        pending.done = True
        self._in_flight = None
        if self._waiting:
            self._send_next()

    def _fail(self, err: Exception, why: str = ""):
        # The pool is broken: every submitted batch is lost with it (the caller rebuilds the pool).
        self._in_flight, self._waiting = None, deque()
        raise WorkerCrashed(f"an evaluation worker died: {err!r}{why}") from err

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
