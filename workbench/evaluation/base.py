"""The evaluation interface: a batch of hypotheses in, projected poses and log-likelihoods out. The estimators see
only ``Evaluator``; where the work runs (this process, a pool of local workers, or Ray actors on a cluster) is the
evaluator's business. ``submit`` hands a batch over and returns at once where the work runs elsewhere, so that the
caller can prepare the next batch meanwhile; ``evaluate`` is ``submit(...).result()``. ``map`` runs the search's own
pure work (candidate fits) on the same workers, so that they do not wait while the main process fits.

Each evaluation is independent of every other (physics rebuilds its world per particle), so splitting a batch
across workers never changes a result; every evaluator that splits one splits it as ``split_batch`` does.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, ClassVar, Protocol

import numpy as np

from workbench.errors import InputError
from workbench.geometry import check_rigid
from workbench.inference.smc.particleset import Rows
from workbench.problem.problem import Problem
from workbench.problem.scene import Table

STAGES = ("projection", "render", "likelihood")


@dataclass
class Evaluation(Rows):
    """Results for B hypotheses: ``projected`` (B, K, 4, 4) resting poses, ``loglik`` (B,) (-inf where physics
    failed), ``status`` (B,) physics status codes, ``floor_gain`` (B,) the part of ``loglik`` the clutter floor
    adds (``likelihood.ImageTerms.scene``; 0 where it is off or physics failed), ``timings`` seconds spent per stage
    (summed over workers). Indexing, concatenation and interleaving as for every ``particleset.Rows``."""

    projected: np.ndarray
    loglik: np.ndarray
    status: np.ndarray
    floor_gain: np.ndarray
    timings: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))

    ROWS: ClassVar[tuple[str, ...]] = ("projected", "loglik", "status", "floor_gain")

    @classmethod
    def merge_other(cls, parts: list["Evaluation"]) -> dict:
        """A batch made of parts took the time of all of them."""
        return {"timings": {s: sum(p.timings[s] for p in parts) for s in STAGES}}


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
        physics (``inference.answer.settle``): ``projected`` is then the hypotheses, with status ``STATUS_AS_GIVEN``."""
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


def _centres(T_world_obj: np.ndarray, problem: Problem) -> np.ndarray:
    """Every object's mesh bounding-box centre in the camera frame -> (B, K, 3) m, for B scenes (B, K, 4, 4)."""
    centres = np.stack([m.mesh.bounds.mean(axis=0) for m in problem.models])  # (K, 3) m, object frame
    world = np.einsum("bkij,kj->bki", T_world_obj[..., :3, :3], centres) + T_world_obj[..., :3, 3]
    T = problem.camera.T_cam_world
    return world @ T[:3, :3].T + T[:3, 3]


def _pixels(cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image coordinates (u, v) of camera-frame points (..., 3) under intrinsics ``K``; nan behind the camera, and
    inf or nan for absurd poses, both of which every comparison reads as outside the image."""
    with np.errstate(all="ignore"):
        z = np.where(cam[..., 2] > 0, cam[..., 2], np.nan)
        return K[0, 0] * cam[..., 0] / z + K[0, 2], K[1, 1] * cam[..., 1] / z + K[1, 2]


def in_view(T_world_obj: np.ndarray, problem: Problem) -> np.ndarray:
    """Whether every object's centre (its mesh's bounding-box centre) projects into the camera's full image, in
    front of it -> (B,) bool, for B scenes (B, K, 4, 4) in the table frame. An object listed for a frame shows itself
    there: without this, the search parks an object mostly out of view over clutter that the image's border cuts,
    whose cut outline any shape fits (real-shape frame 22: the sugar box over a distractor can at the border, its
    centre 13 px beyond it, outscored the box where it stands in full view). Every annotated object of the shared
    sets has its centre at least 88 px inside the image."""
    camera = problem.camera
    u, v = _pixels(_centres(T_world_obj, problem), camera.K)
    inside = (u >= 0) & (u <= camera.width) & (v >= 0) & (v <= camera.height)  # False where nan
    return np.all(inside, axis=1)


def in_region(T_world_obj: np.ndarray, table: Table, margin: float) -> np.ndarray:
    """Whether each object's origin (B, K, 4, 4 table frame) lies within ``margin`` (m) of the table's object
    region -> (B, K) bool."""
    xy = T_world_obj[:, :, :2, 3]
    lo, hi = np.asarray(table.region_min) - margin, np.asarray(table.region_max) + margin
    return np.all((xy >= lo) & (xy <= hi), axis=-1)


def hidden_behind_region(T_world_obj: np.ndarray, problem: Problem) -> np.ndarray:
    """Whether each object's centre lies behind what the object region shows -> (B, K) bool, for B scenes
    (B, K, 4, 4): its pixel on the render grid holds a reading of ``Problem.hiders`` at least ``HIDDEN_BEHIND`` (m)
    nearer the camera. The region bounds what is seen, so an object hidden behind the objects seen may rest beyond
    it: generated frame 23's hidden box rests 7 cm beyond the region, behind the tall box that hides it, and every
    object under 10 % visible in the generated sets rests 1-7 cm beyond it."""
    cam = _centres(T_world_obj, problem)
    hiders, observed = problem.hiders, problem.observed
    h, w = hiders.shape
    u, v = _pixels(cam, problem.render_camera.K)
    on_grid = (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)  # False where nan
    iu = np.clip(np.round(np.nan_to_num(u)), 0, w - 1).astype(int)
    iv = np.clip(np.round(np.nan_to_num(v)), 0, h - 1).astype(int)
    return on_grid & hiders[iv, iu] & (observed[iv, iu] <= cam[..., 2] - HIDDEN_BEHIND)


# How far (m) behind a reading of the region an object's centre must lie to count as hidden by it: more than the
# depth noise, so that an object laid on clutter just beyond the region, level with the region's readings, is not.
HIDDEN_BEHIND = 0.02


def admissible(T_world_obj: np.ndarray, problem: Problem) -> np.ndarray:
    """Whether a scene may explain the frame at all -> (B,) bool: every object within ``region_margin`` of the object
    region (``in_region``) or hidden behind what it shows (``hidden_behind_region``), and in view (``in_view``).
    Scenes that are not get status ``STATUS_OUTSIDE`` and no likelihood."""
    near = in_region(T_world_obj, problem.table, problem.config.region_margin)
    if not near.all():
        near = near | hidden_behind_region(T_world_obj, problem)
    return np.all(near, axis=1) & in_view(T_world_obj, problem)


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


Run = Callable[[Callable, list[tuple]], list]  # Evaluator.map: run(fn, calls) -> [fn(problem, *args) for args in calls]


def run_here(problem: Problem) -> Run:
    """``Evaluator.map`` done in this process: ``run(fn, calls)`` -> ``[fn(problem, *args) for args in calls]``."""
    return lambda fn, calls: [fn(problem, *args) for args in calls]


def split_calls(calls: list[tuple], parts: int) -> list[list[tuple]]:
    """``calls`` dealt out to up to ``parts`` workers, call i to worker i mod ``parts``, non-empty -> chunks.

    Dealt, not cut into contiguous chunks: neighbouring calls cost alike (the library's fits of one cluster, object
    after object), so contiguous chunks gave one worker the largest cluster's fits while the other idled. Each call
    runs alone, so the results do not depend on which worker ran it."""
    return [calls[i::parts] for i in range(min(parts, len(calls)))]


def joined(parts: list[list]) -> list:
    """The results of ``split_calls``' chunks, back in one list in call order."""
    out: list = [None] * sum(len(part) for part in parts)
    for i, part in enumerate(parts):
        out[i::len(parts)] = part
    return out


class WorkerCrashed(RuntimeError):
    """A worker process died mid-evaluation; the pool must be rebuilt."""
