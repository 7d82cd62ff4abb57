"""The estimator process: owns the problem, the worker pool and the ``Estimator``, and answers commands.

It runs in a ``spawn``ed process (forking after an OpenGL context exists hangs the child) so that the browser
server never waits for an iteration: the server puts commands on a queue and reads messages from a pipe (see
``EngineClient``). Commands are drained between iterations, so a Pause takes effect after the iteration in
progress.

A dead evaluation worker surfaces as ``WorkerCrashed`` (or a broken pipe): the pool is rebuilt and the iteration
retried once, and the user is told. If this whole process dies, ``EngineClient`` (the server side) restarts it
and reloads the frame.
"""

from __future__ import annotations

import atexit
import logging
import multiprocessing as mp
import os
import queue
import shutil
import signal
import tempfile
import threading
import time
import traceback
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from workbench.app import protocol as p
from workbench.errors import InputError

log = logging.getLogger(__name__)

DEMO_DIR = Path(__file__).resolve().parents[2] / "assets" / "demo"
DEFAULT_DISPLAY = 512  # particles per snapshot; the rest are the least likely and add only clutter
CRASH_ERRORS = (EOFError, BrokenPipeError, ConnectionError)


# ---------------------------------------------------------------------------------------------------------------
# Loading


def demo_dataset(cache: Callable[[], Path]) -> Path:
    """The bundled demo dataset if the checkout has one, else a fresh one written by ``synth.make_demo`` into the
    folder ``cache()`` gives."""
    if (DEMO_DIR / "models").is_dir():
        return DEMO_DIR
    from workbench.synth import make_demo

    out = cache() / "demo"
    if not (out / "models").is_dir():
        make_demo(out)
    return out


def load(source: p.Source, likelihood: str, cache: Callable[[], Path]):
    """-> (frame, problem) for ``source``; raises ``InputError`` naming the file at fault."""
    from workbench import bop
    from workbench.likelihood import LikelihoodConfig
    from workbench.pipeline import load_bop_problem
    from workbench.problem import ProblemConfig

    dataset = demo_dataset(cache) if source.demo else source.dataset
    if dataset is None:
        raise InputError(None, "no dataset given: type a BOP dataset folder or load the demo")
    dataset = Path(dataset).expanduser()
    if not dataset.exists():
        raise InputError(dataset, "no such file or folder")
    scene_id, im_id = source.scene_id, source.im_id
    if scene_id is None or im_id is None:
        frames = [f for f in bop.list_frames(dataset) if scene_id is None or f[0] == scene_id]
        if not frames:
            raise InputError(dataset, f"no frames{'' if scene_id is None else f' in scene {scene_id}'}")
        scene_id, im_id = frames[0] if im_id is None else (frames[0][0], im_id)
    config = ProblemConfig(likelihood=LikelihoodConfig(model=likelihood))
    frame, problem = load_bop_problem(dataset, scene_id, im_id, config=config)
    return frame, problem


def title_of(source: p.Source, frame) -> str:
    name = "demo" if source.demo else Path(source.dataset).name
    return f"{name} · scene {frame.scene_id} · frame {frame.im_id}"


# ---------------------------------------------------------------------------------------------------------------
# The engine


class Engine:
    def __init__(self, results: "Outbox", workers: int):
        self.results = results
        self.workers = workers
        self._cache: Path | None = None
        self.problem = None
        self.frame = None
        self.estimator = None
        self.evaluator = None
        self.explainer = None  # a LocalEvaluator in this process, for one particle's per-pixel likelihood
        self.config = None
        self.running = False
        self.stop_on_convergence = True
        self.max_display = DEFAULT_DISPLAY
        self.order = np.zeros(0, int)  # particle indices of the last snapshot, most likely first
        self.rank = 0

    def cache(self) -> Path:
        """A scratch folder of this process (made on first use, removed by ``close``)."""
        if self._cache is None:
            self._cache = Path(tempfile.mkdtemp(prefix="workbench-app-"))
        return self._cache

    # -- commands

    def handle(self, cmd) -> None:
        if isinstance(cmd, p.Load):
            self.load(cmd)
        elif isinstance(cmd, p.Reset):
            self.reset(cmd.config, cmd.likelihood)
        elif isinstance(cmd, p.SetConfig):
            self.set_config(cmd.config)
        elif isinstance(cmd, p.Select):
            self.rank = max(0, int(cmd.rank))
            self.publish_chosen()
        elif isinstance(cmd, p.SetDisplay):
            self.max_display = max(1, int(cmd.max_particles))
            if self.estimator is not None and self.estimator.loglik is not None:
                self.publish()
        elif isinstance(cmd, p.Step):
            if not self.running:
                self.step()
        elif isinstance(cmd, p.Run):
            self.start(cmd.stop_on_convergence)
        elif isinstance(cmd, p.Pause):
            if self.running:
                self.running = False
                self.send_state("paused")

    def load(self, cmd: p.Load) -> None:
        cmd.config.validate()
        frame, problem = load(cmd.source, cmd.likelihood, self.cache)  # on failure the old run stays
        from workbench.app.observation import build_view

        view = build_view(frame, problem, title_of(cmd.source, frame))
        self.close_evaluators()
        self.frame, self.problem, self.config = frame, problem, cmd.config
        self.results.put(p.Loaded(cmd.source, view))
        self.new_estimator()

    def reset(self, config, likelihood: str) -> None:
        if self.problem is None:
            raise InputError(None, "nothing is loaded: load a dataset or the demo first")
        config.validate()
        self.config = config
        if likelihood != self.problem.config.likelihood.model:
            likelihood_config = replace(self.problem.config.likelihood, model=likelihood)
            likelihood_config.validate()
            self.problem = replace(self.problem, config=replace(self.problem.config, likelihood=likelihood_config))
            self.close_evaluators()  # the workers hold the old problem
        self.new_estimator()

    def set_config(self, config) -> None:
        config.validate()
        self.config = config
        if self.estimator is not None:
            self.estimator.set_config(config)

    def new_estimator(self) -> None:
        from workbench.estimators import Estimator

        self.running = False
        if self.evaluator is None:
            self.evaluator = self.make_evaluator()
        self.estimator = Estimator(self.problem, self.config, self.evaluator)
        self.order = np.zeros(0, int)
        self.send_state("reset")

    def make_evaluator(self, crash: BaseException | None = None):
        from workbench.evaluation import make_evaluator

        evaluator = make_evaluator(self.problem, self.workers)
        # The pids serve the status line and the crash tests; a LocalEvaluator has none.
        pids = getattr(evaluator, "pids", [])
        reason = "" if crash is None else f"{type(crash).__name__}: {crash}"
        self.results.put(p.Workers(pids, crash is not None, reason))
        return evaluator

    def close_evaluators(self) -> None:
        for ev in {id(e): e for e in (self.evaluator, self.explainer) if e is not None}.values():
            try:
                ev.close()
            except Exception:  # a crashed pool may fail to close cleanly; it is being replaced anyway
                log.exception("closing an evaluator")
        self.evaluator = self.explainer = None

    def restart_workers(self, err: BaseException) -> None:
        try:
            self.evaluator.close()
        except Exception:
            log.exception("closing a crashed pool")
        if self.explainer is self.evaluator:
            self.explainer = None
        self.evaluator = self.make_evaluator(crash=err)
        self.estimator.evaluator = self.evaluator

    # -- running

    def start(self, stop_on_convergence: bool) -> None:
        if self.estimator is None:
            raise InputError(None, "nothing is loaded: load a dataset or the demo first")
        self.stop_on_convergence = stop_on_convergence
        if self.finished():
            self.results.put(p.Failure(
                "Nothing to run",
                f"the run is at iteration {self.estimator.iteration} of {self.config.iterations}"
                + (" and has converged" if self.estimator.converged else "")
                + ": raise the iteration budget, press Step, or Reset",
            ))
            return
        self.running = True
        self.send_state("running")

    def finished(self) -> bool:
        est = self.estimator
        return est.iteration >= self.config.iterations or (
            self.stop_on_convergence and est.iteration >= 0 and est.converged
        )

    def step(self) -> None:
        from workbench.evaluation import WorkerCrashed

        if self.estimator is None:
            raise InputError(None, "nothing is loaded: load a dataset or the demo first")
        try:
            report = self.estimator.step()
        except (WorkerCrashed, *CRASH_ERRORS) as err:
            self.restart_workers(err)
            report = self.estimator.step()  # a second crash in a row is a Failure for the user
        if self.running and self.finished():
            self.running = False
        self.publish(report)
        if not self.running:
            self.send_state("converged" if report.converged else "done" if self.finished() else "paused")

    def publish(self, report=None) -> None:
        est = self.estimator
        if report is None:
            if not est.history:
                return
            report = est.history[-1]
        order = np.argsort(-est.loglik, kind="stable")  # -inf (failed physics) last
        self.order = order
        top = order[: self.max_display]
        weights = est.weights()
        cloud = p.ParticleCloud(
            iteration=est.iteration,
            n_total=len(order),
            poses=est.projected[top].astype(np.float32),
            weights=weights[top],
            loglik=est.loglik[top],
            status=est.status[top],
        )
        self.results.put(p.Snapshot(report.as_dict(), cloud, self.running, self.config.particles))
        self.publish_chosen()

    def publish_chosen(self) -> None:
        if self.estimator is None or len(self.order) == 0:
            return
        from workbench.evaluation import LocalEvaluator
        from workbench.likelihood import predicted_depth

        est = self.estimator
        rank = min(self.rank, len(self.order) - 1)
        i = int(self.order[rank])
        if self.explainer is None:
            self.explainer = self.evaluator if isinstance(self.evaluator, LocalEvaluator) else LocalEvaluator(self.problem)
        after = est.projected[i]
        rendered, pixels = self.explainer.explain(after)
        predicted = predicted_depth(rendered[None], self.problem.background)[0]
        observed = self.problem.observed
        residual = np.where((observed > 0) & (predicted > 0), observed - predicted, np.nan).astype(np.float32)
        self.results.put(p.Chosen(
            iteration=est.iteration,
            rank=rank,
            index=i,
            loglik=float(est.loglik[i]),
            weight=float(est.weights()[i]),
            status=int(est.status[i]),
            before=est.hypotheses[i].copy(),
            after=after.copy(),
            pixel_loglik=pixels.astype(np.float32),
            residual=residual,
        ))

    def send_state(self, reason: str) -> None:
        it = -1 if self.estimator is None else self.estimator.iteration
        self.results.put(p.RunState(self.running, it, reason))

    def fail(self, err: BaseException) -> None:
        """Tell the user; stop running; keep serving."""
        self.running = False
        if isinstance(err, InputError):
            self.results.put(p.Failure("Input error", err.problem, err.path))
        else:
            log.error("engine error\n%s", traceback.format_exc())
            self.results.put(p.Failure(f"Estimator error ({type(err).__name__})", str(err) or repr(err)))
        self.send_state("error")

    def close(self) -> None:
        self.close_evaluators()
        if self._cache is not None:
            shutil.rmtree(self._cache, ignore_errors=True)


class Outbox:
    """The engine's end of the results pipe, with a queue's ``put``."""

    def __init__(self, conn):
        self.conn = conn

    def put(self, msg) -> None:
        self.conn.send(msg)


def engine_main(commands: "mp.Queue", results, workers: int) -> None:
    """Entry point of the spawned process. ``results``: the writing end of a one-way pipe."""
    # Ctrl-C in a terminal reaches the whole process group; the server shuts this process down in order instead.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=logging.WARNING, format="engine: %(message)s")
    outbox = Outbox(results)
    engine = Engine(outbox, workers)
    parent = mp.parent_process()
    try:
        outbox.put(p.Ready(os.getpid()))
        while True:
            try:
                # Block briefly while idle; never while running, so iterations follow each other at once.
                cmd = commands.get(timeout=0.5) if not engine.running else commands.get_nowait()
            except queue.Empty:
                cmd = None
            if isinstance(cmd, p.Shutdown):
                break
            try:
                if cmd is not None:
                    engine.handle(cmd)
                    continue  # drain every queued command before the next iteration
                if engine.running:
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
                 on_restart: Callable[[int | None, bool], None]):
        self.workers = workers
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
            target=engine_main, args=(self.commands, writer, self.workers), name="workbench-engine"
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
