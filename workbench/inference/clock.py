"""Where a run's wall time goes, and when it must stop: ``StageClock``.

The search names its stages (``with clock.stage("polish"):``). The clock charges the wall time between two marks to
the innermost open stage, so that the stages' times add up to the run's. Within a stage, the time spent waiting for
the evaluator (``with clock.waiting():``) is kept apart from this process's own work, and the stage is credited with
the hypotheses it had evaluated and the workers' own seconds for them (physics, rendering, likelihood: the
``Evaluation.timings``).

A budget (s) makes a run anytime: ``over(share)`` says whether that share of it is spent, and ``cut(stage)`` records
a stage the budget skipped, which the answer reports (``Estimator.cut_short``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

from workbench.evaluation.base import STAGES as WORKER_STAGES

# The share of a budget the iterations (with their polish) may spend; the rest is the answer's: settling, the turns and
# the posterior sweep, which take about a tenth of a real frame's time without a budget, and more of a short one
# (docs/journal/2026-12.md, "Anytime").
ITERATE_SHARE = 0.75
# The stages in the order a run meets them (the profile's rows and bars); a stage not listed goes last.
ORDER = ("load", "start", "library", "proposals", "filter", "sink", "polish", "assemblies", "near misses", "floor",
         "settle", "turns", "posterior", "other")
# What each stage is doing, in words (the workbench's status while it runs).
DOING = {"load": "loading the frame", "start": "starting: candidates and the first particles",
         "library": "fitting candidates to the points", "proposals": "moving the particles",
         "filter": "stepping the filter", "sink": "fitting how deep the objects sit",
         "polish": "polishing the estimate", "assemblies": "assembling whole scenes from the candidates",
         "near misses": "fitting the scenes that nearly won", "floor": "weighing the clutter floor in",
         "settle": "settling the answer on the depth", "turns": "trying each object's turns",
         "posterior": "computing the posterior", "other": "between stages"}


@dataclass
class StageTotals:
    """One stage's share of a run: ``own`` seconds of this process's work, ``waited`` seconds waiting for the
    evaluator's workers (their batches, and the fits they ran for the search), ``evaluations`` hypotheses projected
    and weighed, ``scored`` hypotheses weighed as given (no physics), ``worker`` the workers' CPU seconds per stage of
    an evaluation (summed over workers)."""

    own: float = 0.0
    waited: float = 0.0
    evaluations: int = 0
    scored: int = 0
    worker: dict[str, float] = field(default_factory=lambda: dict.fromkeys(WORKER_STAGES, 0.0))

    @property
    def wall(self) -> float:
        return self.own + self.waited


class StageClock:
    """Wall time per named stage of one run, and the run's budget (``budget_s`` seconds, None: none).
    ``started``: the ``now()`` the run's time counts from, if earlier than the clock (a frame's loading and its
    workers' start: the stage "load"). ``on_stage(name)``: told whenever the innermost open stage changes (the
    workbench's status). ``now``: the clock read (seconds, monotonic), replaceable in tests."""

    def __init__(self, budget_s: float | None = None, started: float | None = None,
                 on_stage: Callable[[str], None] | None = None, now: Callable[[], float] = time.perf_counter):
        self.budget_s = budget_s
        self.on_stage = on_stage
        self._now = now
        self.stages: dict[str, StageTotals] = {}
        self._open = ["load"]
        self.started = self._mark = now() if started is None else started
        self._charge()
        self._open = ["other"]
        self.cuts: list[str] = []  # the stages the budget skipped, each with what would have followed it

    # ------------------------------------------------------------------------------------------------- charging
    def _charge(self, waited: bool = False) -> None:
        t = self._now()
        totals = self.totals(self._open[-1])
        if waited:
            totals.waited += t - self._mark
        else:
            totals.own += t - self._mark
        self._mark = t

    def totals(self, stage: str) -> StageTotals:
        return self.stages.setdefault(stage, StageTotals())

    @property
    def current(self) -> str:
        return self._open[-1]

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """The time until the block ends is ``name``'s, less the stages opened inside it."""
        self._charge()
        self._open.append(name)
        self._tell()
        try:
            yield
        finally:
            self._charge()
            self._open.pop()
            self._tell()

    def _tell(self) -> None:
        if self.on_stage is not None and self._open[-1] != "other":
            self.on_stage(self._open[-1])

    @contextmanager
    def waiting(self) -> Iterator[None]:
        """The block's time is the current stage's wait for the evaluator, not its own work."""
        self._charge()
        try:
            yield
        finally:
            self._charge(waited=True)

    def count(self, n: int, projected: bool, timings: dict[str, float]) -> None:
        """``n`` hypotheses evaluated for the current stage (``projected``: through physics, else as given), with the
        workers' seconds per stage of an evaluation (``Evaluation.timings``)."""
        totals = self.totals(self.current)
        if projected:
            totals.evaluations += n
        else:
            totals.scored += n
        for name in WORKER_STAGES:
            totals.worker[name] += float(timings.get(name, 0.0))

    # --------------------------------------------------------------------------------------------------- budget
    def elapsed(self) -> float:
        """Wall seconds since the clock started."""
        return self._now() - self.started

    def over(self, share: float = 1.0) -> bool:
        """Whether ``share`` of the budget is spent (never without one)."""
        return self.budget_s is not None and self.elapsed() >= share * self.budget_s

    def cut(self, stage: str) -> None:
        """The budget skipped ``stage`` (and what follows it in its part of the run: the iterations, or the answer)."""
        if stage not in self.cuts:
            self.cuts.append(stage)

    @property
    def cut_short(self) -> str | None:
        """The stages the budget skipped, e.g. "iterations, turns" (the iterations stopped early, and the answer
        from its turns on), or None."""
        return ", ".join(self.cuts) or None

    # ------------------------------------------------------------------------------------------------- reading
    def ordered(self) -> list[tuple[str, StageTotals]]:
        """The stages met so far, in ``ORDER``."""
        self._charge()
        return self.ordered_items(self.stages)

    @staticmethod
    def ordered_items(stages: dict[str, StageTotals]) -> list[tuple[str, StageTotals]]:
        """``stages`` (name -> totals) as (name, totals) pairs in ``ORDER``, others after them."""
        rank = {name: i for i, name in enumerate(ORDER)}
        return sorted(stages.items(), key=lambda item: rank.get(item[0], len(ORDER)))
