"""`workbench bench --profile DATASET --scene S --frame F [--tracked-from A]`: where one frame's wall time goes,
estimated from scratch or tracked from frame A on.

The frame is estimated as `workbench estimate` does it (the default settings unless overridden), with its stages
timed by the run's ``inference.clock.StageClock``: per stage this process's own work, its wait for the evaluation
workers, the hypotheses it had evaluated and the workers' seconds for them (physics, rendering, likelihood). Printed
as a table and drawn as a stacked bar (PNG). Numbers, not assertions: docs/benchmarks.md quotes them with the machine
and the command.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from PIL import Image, ImageDraw

from workbench.evaluation import make_evaluator
from workbench.evaluation.base import STAGES as WORKER_STAGES
from workbench.inference.clock import StageTotals
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator
from workbench.problem.build import load_bop_problem
from workbench.track.config import TrackConfig
from workbench.track.sequence import Tracker


@dataclass
class FrameProfile:
    """One frame's run: ``stages`` (name, totals) in the order met, ``wall`` seconds in all (loading included),
    ``workers`` evaluation processes, ``iterations`` run, ``objects`` in the frame and where the budget cut it
    (``cut_short``, None where it finished)."""

    frame: str
    stages: list[tuple[str, StageTotals]]
    wall: float
    workers: int
    iterations: int
    objects: int
    cut_short: str | None = None

    @property
    def worker_seconds(self) -> dict[str, float]:
        """The workers' CPU seconds per stage of an evaluation, summed over the run."""
        return {s: sum(t.worker[s] for _, t in self.stages) for s in WORKER_STAGES}

    @property
    def workers_other(self) -> float:
        """Worker-seconds the workers were not evaluating while this process waited for them: the search's fits
        they ran (``Evaluator.map``), transfer and idling on an uneven split."""
        waited = sum(t.waited for _, t in self.stages)
        return max(0.0, waited * self.workers - sum(self.worker_seconds.values()))


def profile_frame(dataset: Path, scene_id: int, im_id: int, config: EstimatorConfig, workers: int = 2,
                  split: str | None = None) -> FrameProfile:
    """Estimate one frame as `workbench estimate` would, timed by stage -> its profile."""
    t0 = time.perf_counter()
    _, problem = load_bop_problem(dataset, scene_id, im_id, split)
    evaluator = make_evaluator(problem, workers)
    try:
        estimator = Estimator(problem, config, evaluator)
        estimator.run(started=t0)
    finally:
        evaluator.close()
    wall = time.perf_counter() - t0
    return FrameProfile(f"{scene_id}/{im_id}", estimator.clock.ordered(), wall, workers, estimator.iteration + 1,
                        problem.n_objects, estimator.cut_short)


def profile_tracked(dataset: Path, scene_id: int, frames: list[int], config: EstimatorConfig, track: TrackConfig,
                    workers: int = 2, split: str | None = None) -> FrameProfile:
    """Track ``frames`` (image ids in order, the first estimated from scratch) as `workbench track` would, and
    profile the last one: its search's stages, "load" for the tracker's work before the search (reading the frame,
    its table, the lost check) and "other" with what it hands the next frame -> its profile."""
    tracker = Tracker(dataset, scene_id, frames, config, track, workers=workers, split=split)
    try:
        for im_id in frames[:-1]:
            tracker.step(im_id)
        t0 = time.perf_counter()
        done = tracker.advance(frames[-1])
        clock = done.estimator.clock
        stages = dict(clock.ordered())  # "other" charged up to here
        t1 = time.perf_counter()
        tracker.resume(done.frame, done.problem, done.estimator, done.best, done.lost)
        wall = time.perf_counter() - t0
    finally:
        tracker.close()
    stages.setdefault("load", StageTotals()).own += clock.started - t0
    stages.setdefault("other", StageTotals()).own += wall - (t1 - t0)
    return FrameProfile(f"{scene_id}/{frames[-1]} ({done.status})", clock.ordered_items(stages), wall, workers,
                        done.estimator.iteration + 1, done.problem.n_objects, done.estimator.cut_short)


def profile_table(profile: FrameProfile) -> list[str]:
    """The profile as a markdown table: per stage its wall seconds (own work + waiting for the workers), share of
    the frame, evaluations (projected + scored as given), and the workers' seconds for them; then the workers'
    totals."""
    lines = [f"frame {profile.frame}: {profile.objects} objects, {profile.wall:.1f} s, {profile.iterations} "
             f"iterations, {profile.workers} workers" + ("" if profile.cut_short is None
                                                          else f", cut short by the budget at {profile.cut_short}"),
             "",
             "| stage | wall s | own s | waiting s | share | projected | scored | physics s | render s "
             "| likelihood s |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, t in profile.stages:
        if t.wall < 0.005 and not (t.evaluations or t.scored):
            continue
        w = t.worker
        lines.append(f"| {name} | {t.wall:.2f} | {t.own:.2f} | {t.waited:.2f} | {100 * t.wall / profile.wall:.0f} % "
                     f"| {t.evaluations} | {t.scored} | {w['projection']:.2f} | {w['render']:.2f} "
                     f"| {w['likelihood']:.2f} |")
    ws, all_ = profile.worker_seconds, [t for _, t in profile.stages]
    lines.append(f"| **all** | {sum(t.wall for t in all_):.2f} | {sum(t.own for t in all_):.2f} "
                 f"| {sum(t.waited for t in all_):.2f} | | {sum(t.evaluations for t in all_)} "
                 f"| {sum(t.scored for t in all_)} | {ws['projection']:.2f} | {ws['render']:.2f} "
                 f"| {ws['likelihood']:.2f} |")
    lines.append("")
    lines.append(f"workers' seconds: physics {ws['projection']:.1f}, rendering {ws['render']:.1f}, likelihood "
                 f"{ws['likelihood']:.1f}, other (the search's fits, transfer, idle) {profile.workers_other:.1f}")
    return lines


# One colour per stage, in inference.clock.ORDER; waiting is drawn lighter.
PALETTE = [(140, 140, 140), (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
           (140, 86, 75), (227, 119, 194), (188, 189, 34), (23, 190, 207), (70, 70, 200), (200, 70, 70),
           (70, 160, 120), (60, 60, 60), (120, 120, 40)]
WORKER_COLOURS = {"projection": (44, 120, 44), "render": (31, 90, 160), "likelihood": (200, 120, 20),
                  "other": (200, 200, 200)}


def _lighter(c: tuple[int, int, int]) -> tuple[int, int, int]:
    return tuple(int(v + (255 - v) * 0.55) for v in c)


def profile_png(profiles: list[FrameProfile], path: Path, title: str = "") -> None:
    """Per profile two stacked bars: this process's wall time by stage (each stage's own work solid, its wait for
    the workers lighter), and the workers' time per worker (physics, rendering, likelihood, other), with a legend;
    a PNG at ``path``."""
    from workbench.inference.clock import ORDER

    names = [n for n in ORDER if any(n == s for p in profiles for s, _ in p.stages)]
    names += sorted({s for p in profiles for s, _ in p.stages} - set(names))
    colour = {n: PALETTE[i % len(PALETTE)] for i, n in enumerate(names)}
    width, bar_h, left, top = 900, 26, 150, 40
    legend_h = 20 * ((len(names) + 4 + 3) // 4)
    height = top + len(profiles) * (2 * bar_h + 40) + 50 + legend_h
    image = Image.new("RGB", (width, height), "white")
    draw = ImageDraw.Draw(image)
    longest = max(p.wall for p in profiles)
    scale = (width - left - 30) / max(longest, 1e-9)
    draw.text((10, 10), (title or "where a frame's wall time goes") + " (a stage's wait for the workers drawn lighter)",
              fill="black")
    y = top
    for p in profiles:
        draw.text((10, y + 6), f"frame {p.frame}", fill="black")
        draw.text((10, y + bar_h + 10), "workers (per worker)", fill="black")
        x = left
        for name, t in p.stages:
            for seconds, c in ((t.own, colour[name]), (t.waited, _lighter(colour[name]))):
                if seconds * scale >= 0.5:
                    draw.rectangle([x, y, x + seconds * scale, y + bar_h], fill=c)
                    x += seconds * scale
        draw.text((x + 4, y + 6), f"{p.wall:.1f} s", fill="black")
        x, yw = left, y + bar_h + 6
        parts = {**p.worker_seconds, "other": p.workers_other}
        for name, seconds in parts.items():
            w = seconds / p.workers * scale
            if w >= 0.5:
                draw.rectangle([x, yw, x + w, yw + bar_h], fill=WORKER_COLOURS[name])
                x += w
        y += 2 * bar_h + 40
    # Axis in seconds.
    step = next(s for s in (1, 2, 5, 10, 20, 30, 60, 120) if longest / s <= 10)
    for k in range(int(longest // step) + 1):
        x = left + k * step * scale
        draw.line([x, top - 4, x, y - 30], fill=(225, 225, 225))
        draw.text((x - 6, y - 26), f"{k * step}", fill="black")
    draw.text((left + (width - left) / 2 - 20, y - 12), "seconds", fill="black")
    worker_names = {"projection": "physics", "render": "rendering"}
    entries = [(n, colour[n]) for n in names] + [(f"workers: {worker_names.get(k, k)}", c)
                                                 for k, c in WORKER_COLOURS.items()]
    for i, (name, c) in enumerate(entries):
        lx, ly = 10 + (i % 4) * 220, y + 10 + 20 * (i // 4)
        draw.rectangle([lx, ly, lx + 12, ly + 12], fill=c)
        draw.text((lx + 18, ly), name, fill="black")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    image.save(path)

