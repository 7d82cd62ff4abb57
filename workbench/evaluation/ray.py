"""Ray (`--engine ray`, the optional extra ``workbench[ray]``): one frame's particle batches over Ray actors
(``RayEvaluator``, for `serve`), and the connection to Ray that it and the frame tasks (``workbench.frames``) share:
``RayConfig``, ``connect``, ``disconnect``.

``RayEvaluator`` splits a batch over its actors as ``PoolEvaluator`` splits it over processes, so its results equal a
pool's of the same size. Ray is imported only when something here is called (``require_ray``), so that importing
this module, and everything else, works without it.
"""

from __future__ import annotations

import logging
import os
import socket
from dataclasses import dataclass

import numpy as np

from workbench.errors import InputError
from workbench.evaluation.base import Evaluation, WorkerCrashed, joined, split_batch, split_calls
from workbench.evaluation.local import LocalEvaluator
from workbench.problem.problem import Problem

INSTALL_HINT = "pip install 'workbench[ray]' (in a checkout: .venv/bin/pip install -e '.[ray]')"


@dataclass(frozen=True)
class RayConfig:
    """Where Ray work runs.

    ``address``: None starts a Ray instance on this machine for the run and stops it afterwards; "auto" joins the
    cluster that `ray start` started on this machine; "HOST:PORT" joins that cluster's head node. ``num_cpus``: the
    CPUs of a Ray instance started here (None: all; ignored when joining a cluster). ``max_retries``: how many
    times a frame task is started again after its worker process died (killed, out of memory, node lost) before
    the frame is reported as failed; an error raised by the frame itself (bad input) is reported at once."""

    address: str | None = None
    num_cpus: int | None = None
    max_retries: int = 3

    def validate(self) -> None:
        if self.num_cpus is not None and self.num_cpus < 1:
            raise InputError("num_cpus", f"must be at least 1, got {self.num_cpus}")
        if self.max_retries < 0:
            raise InputError("--max-retries", f"must be 0 or more, got {self.max_retries}")


def require_ray():
    """The ``ray`` module, or InputError saying how to install it."""
    try:
        import ray
    except ImportError as err:
        raise InputError("--engine", f"ray is not installed ({err}); install the extra: {INSTALL_HINT}") from None
    return ray


def check_reachable(address: str | None, timeout_s: float = 5.0) -> None:
    """InputError when ``address`` is HOST:PORT and nothing answers there within ``timeout_s``: Ray itself keeps
    retrying an unreachable head node for many minutes without a word."""
    if address is None or address == "auto":
        return
    scheme, sep, rest = address.partition("://")
    if sep and scheme != "ray":
        raise InputError("--ray-address", f"{address!r} is a web address (Ray's dashboard is http://HOST:8265): give "
                                          "the cluster's HOST:PORT (the port of `ray start --head`, 6379 by "
                                          "default), ray://HOST:PORT or auto")
    host, _, port = (rest if sep else address).rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]  # an IPv6 address, [::1]:6379
    if not host or not port.isdigit() or "[" in host or "]" in host or "/" in host:
        raise InputError("--ray-address", f"expected auto or HOST:PORT (e.g. 10.0.0.5:6379), got {address!r}")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as err:
        raise InputError("--ray-address", f"nothing answers at {address} ({err}): is `ray start --head` running "
                                          "there, and is the port open to this machine?") from None


def connect(config: RayConfig):
    """Connect this process to Ray as ``config`` says (a no-op when it already is) -> the ``ray`` module. A cluster
    that cannot be reached is an InputError naming the address."""
    ray = require_ray()
    if ray.is_initialized():
        return ray
    config.validate()
    check_reachable(config.address)
    from workbench.meshes.heavy import announced

    what = "starting Ray for the run" if config.address is None else f"joining the Ray cluster at {config.address}"
    try:
        with announced(what, cached=False):  # Ray takes from seconds to minutes to start: never silent
            ray.init(
                # "local": a Ray of its own for the run, never a cluster another process started that Ray would find
                # through RAY_ADDRESS or its current-cluster file (the meaning of None)
                address=config.address or "local",
                num_cpus=config.num_cpus if config.address is None else None,
                include_dashboard=False,
                # Task output (pybullet's banner, llvmpipe warnings) would tear the progress bar; errors come back as
                # exceptions and are reported per frame.
                log_to_driver=False,
                logging_level=logging.WARNING,
            )
    except ConnectionError as err:
        raise InputError("--ray-address", f"no Ray cluster reachable at {config.address!r} ({err}); start one with "
                                          "`ray start --head`, or leave out --ray-address to start Ray here. A "
                                          "cluster with token authentication (Ray's default since 2.59) also needs "
                                          "RAY_AUTH_MODE=token and its head's ~/.ray/auth_token here") from None
    return ray


def disconnect() -> None:
    """Leave Ray (and stop the instance ``connect`` started here, if it did)."""
    ray = require_ray()
    if ray.is_initialized():
        ray.shutdown()


def cluster_cpus() -> int:
    """CPUs of the connected cluster, all nodes together."""
    return int(require_ray().cluster_resources().get("CPU", 0))


class _EvaluatorActor:
    """A Ray actor holding one ``LocalEvaluator`` of the problem (its own physics client and renderer)."""

    def __init__(self, problem: Problem):
        # One llvmpipe thread per actor, as in PoolEvaluator's workers: the actors already fill the cores.
        os.environ.setdefault("LP_NUM_THREADS", "1")
        self.evaluator = LocalEvaluator(problem)

    def evaluate(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Evaluation:
        return self.evaluator.evaluate(hypotheses, sink, project)

    def map(self, fn, calls: list[tuple]) -> list:
        return self.evaluator.map(fn, calls)

    def pid(self) -> int:
        return os.getpid()


class _RayPending:
    """A batch submitted to a ``RayEvaluator``: the actors' calls (each actor runs its calls in order)."""

    def __init__(self, ray, calls):
        self._ray, self._calls = ray, calls

    def result(self) -> Evaluation:
        try:
            return Evaluation.concatenate(self._ray.get(self._calls))
        except self._ray.exceptions.RayActorError as err:
            raise WorkerCrashed(f"an evaluation actor died: {err}") from err


class RayEvaluator:
    """The ``Evaluator`` interface over ``actors`` Ray actors of one CPU each, anywhere on the cluster: a batch is
    split into ``actors`` contiguous chunks in order, chunk i to actor i, as ``PoolEvaluator`` splits it over its
    processes, so results equal a pool of the same size bit for bit. The problem is put into the object store once
    and each actor builds its evaluator from it. An actor that dies raises ``WorkerCrashed``, like a pool worker."""

    def __init__(self, problem: Problem, actors: int = 2, config: RayConfig = RayConfig()):
        if actors < 1:
            raise ValueError(f"actors must be >= 1, got {actors}")
        ray = connect(config)
        cpus = cluster_cpus()
        if cpus < actors:
            raise InputError("--workers", f"{actors} evaluation actors need {actors} CPUs; the Ray cluster has {cpus}")
        self._ray = ray
        actor_class = ray.remote(num_cpus=1)(_EvaluatorActor)
        shared = ray.put(problem)
        self._actors = [actor_class.remote(shared) for _ in range(actors)]
        try:
            self._pids = ray.get([a.pid.remote() for a in self._actors])
        except ray.exceptions.RayActorError as err:
            raise WorkerCrashed(f"an evaluation actor died while starting: {err}") from err

    @property
    def pids(self) -> list[int]:
        """Process ids of the actors, on whichever node each runs (for the status line)."""
        return list(self._pids)

    def evaluate(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Evaluation:
        return self.submit(hypotheses, sink, project).result()

    def submit(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> "_RayPending":
        chunks = split_batch(hypotheses, len(self._actors), sink)
        return _RayPending(self._ray, [actor.evaluate.remote(h, s, project)
                                       for actor, (h, s) in zip(self._actors, chunks)])

    def map(self, fn, calls: list[tuple]) -> list:
        """The calls dealt out to the actors (``split_calls``; each runs them after the batches sent before)."""
        chunks = split_calls(list(calls), len(self._actors))
        try:
            parts = self._ray.get([actor.map.remote(fn, chunk) for actor, chunk in zip(self._actors, chunks)])
        except self._ray.exceptions.RayActorError as err:
            raise WorkerCrashed(f"an evaluation actor died: {err}") from err
        return joined(parts)

    def close(self) -> None:
        for actor in self._actors:
            self._ray.kill(actor)
        self._actors = []
