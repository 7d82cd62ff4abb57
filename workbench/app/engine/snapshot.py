"""What the server is sent to show of the run: the most likely particles of an iteration (``protocol.Snapshot``),
and the one the user chose by rank with its per-pixel likelihood (``protocol.Chosen``)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from workbench.app import protocol as p
from workbench.inference.search.moves.registry import MoveKind

# Particles per snapshot; the rest are the least likely and add haze. Their wireframes were about half of every
# software-rendered frame's cost at 64.
DEFAULT_DISPLAY = 32
# Particle outlines drawn in all, over a frame's objects: a frame of K objects draws OUTLINE_BUDGET / K particles by
# default (from MIN_DISPLAY to DEFAULT_DISPLAY). Software WebGL pays per outline: YCB-Video frame 1/1's four objects
# at 32 particles each cost 1.2 times the demo's two objects at 32 a paused frame, at 16 each 0.9 times.
OUTLINE_BUDGET = 64
MIN_DISPLAY = 8


def default_drawn(n_objects: int) -> int:
    """The particles a frame of ``n_objects`` objects draws until the user chooses how many (``OUTLINE_BUDGET``)."""
    return int(np.clip(OUTLINE_BUDGET // max(n_objects, 1), MIN_DISPLAY, DEFAULT_DISPLAY))


def expected_distinct(weights: np.ndarray, n: int) -> float:
    """How many distinct particles systematic resampling of ``weights`` (N,) (normalised) into ``n`` keeps, on
    average. Particle i's share n * w_i of the n evenly spaced pointers holds at least one of them with
    probability min(1, n * w_i) (one uniform offset for all), so the expectation is the sum of those."""
    return float(np.minimum(1.0, n * np.asarray(weights, dtype=np.float64)).sum())


class ParticleDisplay:
    """The particles of the last snapshot by likelihood, how many of them are shown, and the chosen rank."""

    def __init__(self) -> None:
        self.max_display = DEFAULT_DISPLAY
        self.order = np.zeros(0, int)  # particle indices of the last snapshot, most likely first
        self.rank = 0

    def forget(self) -> None:
        """A new run: there is no snapshot to choose from."""
        self.order = np.zeros(0, int)

    def snapshot(self, est, report, running: bool, particles: int, reference: dict[str, float]) -> p.Snapshot:
        """The Snapshot of ``est``'s iteration, ``report`` its row; ``particles``: the configured count (the
        resampling target), ``reference``: the known scenes' log-likelihoods for the Plots tab ("truth_loglik",
        "label_loglik", NaN where unknown)."""
        # -inf (failed physics, or outside the object region) last
        order = np.argsort(-est.particles.loglik, kind="stable")
        self.order = order
        top = order[: self.max_display]
        weights = est.weights()
        cloud = p.ParticleCloud(
            iteration=est.iteration,
            n_total=len(order),
            poses=est.particles.projected[top].astype(np.float32),
            weights=weights[top],
            loglik=est.particles.loglik[top],
            status=est.particles.status[top],
        )
        row = report.as_dict()
        row["distinct_after_resampling"] = expected_distinct(weights, particles)
        clock = est.clock
        row["budget_left_s"] = None if clock.budget_s is None else max(0.0, clock.budget_s - clock.elapsed())
        row["cut_short"] = est.cut_short
        row.update(reference)
        return p.Snapshot(row, cloud, running, particles, est.current_posterior)

    def chosen(self, est, explain: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]) -> p.Chosen | None:
        """The particle at the chosen rank of the last snapshot (None before the first), explained by ``explain``
        (``Evaluators.explain``)."""
        if len(self.order) == 0:
            return None
        rank = min(self.rank, len(self.order) - 1)
        i = int(self.order[rank])
        after = est.particles.projected[i]
        pixels, residual = explain(after)
        return p.Chosen(
            iteration=est.iteration,
            rank=rank,
            index=i,
            loglik=float(est.particles.loglik[i]),
            weight=float(est.weights()[i]),
            status=int(est.particles.status[i]),
            move=MoveKind(int(est.particles.kinds[i])).label,
            before=est.particles.hypotheses[i].copy(),
            after=after.copy(),
            pixel_loglik=pixels.astype(np.float32),
            residual=residual,
        )
