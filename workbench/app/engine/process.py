"""The engine's process: ``engine_main`` runs an ``Engine`` in a ``spawn``ed process, and ``EngineClient`` (the
server side) starts it, sends it commands and reads its messages.

The process is spawned, not forked: forking after an OpenGL context exists hangs the child. The server puts
commands on a queue and reads messages from a pipe, so it never waits for an iteration. Commands are drained
between iterations, so a Pause takes effect after the iteration in progress; label work waits for the drained
queue, so a fast gizmo drag costs one render per pass, not one per mouse event. If the whole process dies,
``EngineClient`` restarts it and the server reloads the frame.
"""

from __future__ import annotations

import atexit
import logging
import multiprocessing as mp
import os
import queue
import signal
import threading
import time
from typing import Callable

from workbench.app import protocol as p
from workbench.app.engine.engine import Engine
from workbench.physics.config import PhysicsConfig

log = logging.getLogger(__name__)


class Outbox:
    """The engine's end of the results pipe, with a queue's ``put``."""

    def __init__(self, conn):
        self.conn = conn

    def put(self, msg) -> None:
        self.conn.send(msg)


def engine_main(commands: "mp.Queue", results, workers: int, ray=None, physics: PhysicsConfig = PhysicsConfig()
                ) -> None:
    """Entry point of the spawned process. ``results``: the writing end of a one-way pipe; ``ray``: a
    evaluation.ray.RayConfig to evaluate on Ray actors; ``physics``: how the frames it loads are simulated."""
    # Ctrl-C in a terminal reaches the whole process group; the server shuts this process down in order instead.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=logging.WARNING, format="engine: %(message)s")
    outbox = Outbox(results)
    engine = Engine(outbox, workers, ray, physics)
    parent = mp.parent_process()
    try:
        outbox.put(p.Ready(os.getpid()))
        while True:
            try:
                # Block briefly while idle or waiting for the server to show the last iteration; never while an
                # iteration may start or label work waits, so iterations follow each other at once and a heatmap
                # follows its edit.
                busy = engine.may_step() or engine.labels.dirty
                cmd = commands.get(timeout=0.5) if not busy else commands.get_nowait()
            except queue.Empty:
                cmd = None
            if isinstance(cmd, p.Shutdown):
                break
            try:
                if cmd is not None:
                    engine.handle(cmd)
                    continue  # drain every queued command before the next iteration
                if engine.labels.dirty:
                    engine.labels.work()  # for the latest labels only: the edits drained above were overwritten
                if engine.may_step():
                    engine.step()
            except Exception as err:  # noqa: BLE001 - every error becomes a message; the loop must survive
                engine.fail(err)
            if parent is not None and not parent.is_alive():
                break
    except BrokenPipeError:  # the server went away while we were telling it something (even about an error)
        pass
    finally:
        engine.close()
        results.close()


# ---------------------------------------------------------------------------------------------------------------
# The server side


class EngineClient:
    """Starts the engine process, sends it commands and hands its messages to ``on_message`` on a reader thread.
    When the process dies it is restarted and ``on_restart(exitcode, gave_up=False)`` is called (the owner then
    reloads); after MAX_RESTARTS deaths within RESTART_WINDOW_S it stops trying and calls it with ``gave_up=True``,
    so a process that cannot even start does not respawn forever.

    Results come over a one-way pipe whose writing end only the engine holds: if the engine dies halfway through
    a message, the reader gets EOF instead of waiting forever for the rest (as it would on a ``Queue``, whose
    writing end this process also holds)."""

    MAX_RESTARTS = 3
    RESTART_WINDOW_S = 60.0

    def __init__(self, workers: int, on_message: Callable[[object], None],
                 on_restart: Callable[[int | None, bool], None], ray=None, physics: PhysicsConfig = PhysicsConfig()):
        self.workers = workers
        self.ray = ray
        self.physics = physics
        self.on_message = on_message
        self.on_restart = on_restart
        self._ctx = mp.get_context("spawn")
        self._stopping = threading.Event()  # no restarts from now on
        self._lock = threading.Lock()
        self._deaths: list[float] = []
        self.process = None
        self.results = None
        self._start_process()
        self._reader = threading.Thread(target=self._read, name="engine-reader", daemon=True)
        self._reader.start()
        # multiprocessing joins non-daemonic children at exit, and the engine waits for our Shutdown: send it first.
        atexit.register(self.stop)

    def _start_process(self) -> None:
        if self.results is not None:
            self.results.close()
        self.commands = self._ctx.Queue()
        self.results, writer = self._ctx.Pipe(duplex=False)
        # Not a daemon: it starts the worker pool, and daemonic processes may not have children. It exits on its
        # own when this process dies (it polls its parent).
        self.process = self._ctx.Process(
            target=engine_main, args=(self.commands, writer, self.workers, self.ray, self.physics),
            name="workbench-engine"
        )
        self.process.start()
        writer.close()  # from now on only the engine holds the writing end

    def send(self, cmd) -> None:
        with self._lock:
            self.commands.put(cmd)

    def _read(self) -> None:
        while True:
            try:
                if not self.results.poll(0.25):
                    if not self.process.is_alive() and not self._stopping.is_set():
                        self._restart()
                    continue
                msg = self.results.recv()
            except (EOFError, OSError):  # the engine is gone, maybe halfway through a message
                if self._stopping.is_set():
                    return
                self.process.join(5)
                self._restart()
                continue
            try:
                self.on_message(msg)
            except Exception:  # a display bug must not stop the reader
                log.exception("handling %s", type(msg).__name__)

    def _restart(self) -> None:
        code = self.process.exitcode
        now = time.monotonic()
        self._deaths = [t for t in self._deaths if now - t < self.RESTART_WINDOW_S] + [now]
        if len(self._deaths) > self.MAX_RESTARTS:
            self._stopping.set()
            self.on_restart(code, True)
            return
        with self._lock:
            self._start_process()
        self.on_restart(code, False)

    def stop(self, timeout: float = 10.0) -> None:
        # The reader keeps draining while the engine exits (a blocked send would hold the engine up), then ends at
        # the pipe's EOF.
        if self._stopping.is_set() and not self.process.is_alive():
            return  # stopped already (or gave up restarting)
        atexit.unregister(self.stop)
        self._stopping.set()
        try:
            self.commands.put(p.Shutdown())
        except (OSError, ValueError):
            pass
        self.process.join(timeout)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(2)
        self._reader.join(5)
        self.commands.cancel_join_thread()
        self.commands.close()
        self.results.close()
