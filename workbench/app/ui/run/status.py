"""What the server knows about the run (``RunView``), and the panel's text about it: the status line, the stage
timings of an iteration, and what physics did to the chosen particle."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from workbench.app import protocol as p
from workbench.app.ui.widgets.colors import named
from workbench.geometry import rotation_angle
from workbench.inference.clock import DOING
from workbench.inference.config import EstimatorConfig
from workbench.physics import STATUS_NAMES


@dataclass
class RunView:
    """What the server knows about the run, for the status line and the tests."""

    iteration: int = -1
    running: bool = False
    reports: list[dict] = field(default_factory=list)
    cloud: p.ParticleCloud | None = None
    chosen: p.Chosen | None = None
    view: p.ObservationView | None = None
    last_state: p.RunState | None = None
    failures: list[p.Failure] = field(default_factory=list)
    worker_pids: list[int] = field(default_factory=list)
    engine_pid: int | None = None
    restarts: int = 0
    pause_requested_at: int | None = None  # the iteration on display when Pause was pressed (this run)
    display_errors: list[str] = field(default_factory=list)  # bugs in drawing a message (logged, kept for tests)
    truth: p.TruthErrors | None = None  # the estimate against the dataset's ground truth, latest iteration
    # The run's own settings where they are not the panel's (a sequence's tracked frame): its budget is its own.
    run_config: EstimatorConfig | None = None
    stage: p.Stage | None = None  # what the run is doing now (while it runs)


def status_markdown(s: RunView, cfg) -> str:
    """The status of the run ``s`` under the settings ``cfg`` (an ``EstimatorConfig``): two short lines, since
    they sit in the panel's fixed top (the iteration's numbers are in the Estimator tab, ``timings_markdown``). A run
    with settings of its own (``s.run_config``) is counted against its own budget."""
    cfg = s.run_config or cfg
    doing = ("" if s.stage is None
             else f": {DOING.get(s.stage.name, s.stage.name)} ({s.stage.seconds:.0f} s into the run)")
    if not s.reports:
        if s.running and s.pause_requested_at is not None:
            return f"No iterations yet ({cfg.iterations} planned) · **stopping after the first**{doing}"
        if s.running:
            return f"No iterations yet ({cfg.iterations} planned) · running{doing}"
        return f"No iterations yet ({cfg.iterations} planned) · paused. Press **Step** or **Run**."
    r = s.reports[-1]
    it = r["iteration"]
    left = r.get("budget_left_s")
    if s.running and s.pause_requested_at is not None:  # Pause was taken: the engine stops between iterations
        state = "**stopping after this iteration**" + doing
    elif s.running:
        state = ("running" if left is None else f"running, {left:.0f} s of the budget left") + doing
    elif r.get("cut_short"):
        state = f"**finished**: the budget cut short {r['cut_short']}"
    elif r["converged"]:
        state = "**finished**: converged"
    elif it >= cfg.iterations:
        state = "**finished**: iteration budget reached"
    else:
        state = "paused"
    counter = f"Iteration {it} of {cfg.iterations}" if it <= cfg.iterations else \
        f"Iteration {it}, {it - cfg.iterations} past the budget of {cfg.iterations}"
    rule = f"< {cfg.converge_position * 100:g} cm, < {cfg.converge_degrees:g}°"
    if r["converged"]:
        conv = f"**converged**: the best scene moved {rule} for {cfg.converge_patience} iterations"
    else:
        calm = r.get("calm")
        if calm is None:  # a report from before the filter's count was sent (a restored session's history)
            calm = 0
            for row in reversed(s.reports):
                if row["best_move_m"] < cfg.converge_position and row["best_move_deg"] < cfg.converge_degrees:
                    calm += 1
                else:
                    break
        last = "" if not np.isfinite(r["best_move_m"]) else \
            f" · last move {r['best_move_m'] * 100:.1f} cm, {r['best_move_deg']:.1f}°"
        # Calm enough to stop, but the run stops only once the clutter floor is weighed in (which restarts the count).
        floor = "" if r.get("floor_in", True) or calm < cfg.converge_patience else " · waiting for the clutter floor"
        conv = f"calm {min(calm, cfg.converge_patience)}/{cfg.converge_patience} ({rule}){last}{floor}"
    return f"**{counter}** · {state}  \n{conv}"


def details_markdown(r: dict) -> str:
    """The iteration's numbers below the status (``r``: its report): the best log-likelihood and the move that
    found it, β, the failures, the acceptance and how far the objects rest below the fitted table."""
    accept = "" if np.isnan(r["accept_rate"]) else f" · accepted {r['accept_rate'] * 100:.0f} %"
    return (f"Iteration {r['iteration']}: best log-lik {r['best_loglik']:.1f} (from a {r.get('best_kind') or 'start'}"
            f" move) · β {r['beta']:.3g} · failed physics or out of region or view {r['n_failed']}{accept} · "
            f"objects rest {r.get('sink_m', 0.0) * 1000:.0f} mm below the fitted table")


def timings_markdown(report: dict) -> str:
    """The Estimator tab's account of an iteration: its numbers (``details_markdown``) and its stage timings."""
    t = report["timings"]
    rows = "\n".join(f"| {stage} | {t.get(stage, 0.0) * 1000:.1f} |"
                     for stage in ("projection", "render", "likelihood", "resampling", "total"))
    return (details_markdown(report) + "\n\n| stage | ms |\n|---|---:|\n" + rows +
            "\n\n<small>projection, render and likelihood are summed over the workers; total is wall time</small>")


def physics_markdown(c: p.Chosen, names: list[str]) -> str:
    """How far physics moved each object of the chosen particle (``names``: the objects' display names)."""
    moved = np.linalg.norm(c.after[:, :3, 3] - c.before[:, :3, 3], axis=-1)
    turned = np.degrees(rotation_angle(np.swapaxes(c.before[:, :3, :3], -1, -2) @ c.after[:, :3, :3]))
    rows = "\n".join(f"| {named(k, name)} | {m * 100:.1f} | {a:.1f} |"
                     for k, (name, m, a) in enumerate(zip(names, moved, turned)))
    return (
        f"Rank **{c.rank}** (particle {c.index}) · log-lik {c.loglik:.1f} · weight {c.weight:.3g} · "
        f"proposed by: {c.move} move · physics: {STATUS_NAMES.get(c.status, c.status)}\n\n"
        f"| object | moved (cm) | turned (°) |\n|---|---:|---:|\n{rows}"
    )
