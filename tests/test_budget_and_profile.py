"""The anytime budget (``EstimatorConfig.budget_s``, ``--budget``) and where a run's time goes (``inference.clock``,
``bench --profile``): the clock's bookkeeping with a clock we step by hand, then real runs on the bundled demo."""

import json
import time

import numpy as np
import pytest
from PIL import Image

from workbench.cli import DEMO_DATASET, main
from workbench.errors import InputError
from workbench.evaluation import PoolEvaluator
from workbench.inference.answer.posterior import Posterior
from workbench.inference.clock import ORDER, StageClock
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator
from workbench.problem.build import load_bop_problem
from workbench.sessions.answer import parse_posterior, posterior_json

DEMO = str(DEMO_DATASET)


class Hand:
    """A clock read we set by hand (seconds)."""

    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_each_second_goes_to_the_innermost_open_stage_and_waits_are_kept_apart():
    hand = Hand()
    clock = StageClock(now=hand, started=98.0)  # two seconds of loading before the clock was made
    with clock.stage("polish"):
        hand.t += 1.0
        with clock.stage("assemblies"):
            hand.t += 3.0
        with clock.waiting():
            hand.t += 2.0
        clock.count(5, True, {"projection": 0.5, "render": 0.25, "likelihood": 0.125})
        clock.count(7, False, {"render": 1.0})
    hand.t += 0.5
    stages = dict(clock.ordered())
    assert stages["load"].own == pytest.approx(2.0)
    assert stages["polish"].own == pytest.approx(1.0) and stages["polish"].waited == pytest.approx(2.0)
    assert stages["assemblies"].own == pytest.approx(3.0) and stages["assemblies"].waited == 0.0
    assert stages["other"].own == pytest.approx(0.5)
    assert sum(t.wall for t in stages.values()) == pytest.approx(clock.elapsed()) == pytest.approx(8.5)
    assert (stages["polish"].evaluations, stages["polish"].scored) == (5, 7)
    assert stages["polish"].worker == {"projection": 0.5, "render": 1.25, "likelihood": 0.125}
    assert [name for name, _ in clock.ordered()] == [n for n in ORDER if n in stages]


def test_a_budget_is_spent_by_share_and_its_cuts_are_named_in_order():
    hand = Hand()
    clock = StageClock(budget_s=4.0, now=hand)
    assert not clock.over(0.75) and clock.cut_short is None
    hand.t += 3.0
    assert clock.over(0.75) and not clock.over()
    clock.cut("iterations")
    hand.t += 1.0
    assert clock.over()
    clock.cut("turns")
    clock.cut("iterations")
    assert clock.cut_short == "iterations, turns"
    assert not StageClock(now=hand).over(0.0)  # no budget: never over


@pytest.mark.parametrize("budget", [0.0, -1.0, float("nan"), float("inf"), 1e6])
def test_an_impossible_budget_is_refused_by_name(budget):
    with pytest.raises(InputError, match="--budget"):
        EstimatorConfig(budget_s=budget).validate("")


def test_a_cut_posterior_keeps_what_was_cut_through_a_session():
    posterior = Posterior([], cut_short="iterations, posterior")
    assert parse_posterior(json.loads(json.dumps(posterior_json(posterior))), 0).cut_short == "iterations, posterior"
    assert "cut_short" not in posterior_json(Posterior([]))  # a whole run's reads as before budgets existed
    assert parse_posterior(posterior_json(Posterior([])), 0).cut_short is None


@pytest.fixture(scope="module")
def demo():
    return load_bop_problem(DEMO, 0, 0)[1]


@pytest.mark.slow
def test_a_run_out_of_budget_answers_from_its_start_and_says_what_it_cut(demo):
    pool = PoolEvaluator(demo, workers=2)
    try:
        # The budget spent before the run begins (as if loading had taken it): the start runs, and nothing after it.
        cut = Estimator(demo, EstimatorConfig(particles=16, iterations=6, seed=0, budget_s=1.0), pool)
        best = cut.run(started=time.perf_counter() - 10.0)
        whole = Estimator(demo, EstimatorConfig(particles=16, iterations=2, seed=0), pool)
        whole.run()
    finally:
        pool.close()
    assert cut.iteration == 0 and cut.cut_short == "iterations, settle"
    assert best.shape == (demo.n_objects, 4, 4) and np.array_equal(best, cut.estimate)  # not settled: no time
    assert cut.posterior.cut_short == "iterations, settle"
    assert [len(o.modes) for o in cut.posterior.objects] == [1] * demo.n_objects
    assert all(0.0 <= o.elsewhere <= 1.0 for o in cut.posterior.objects)
    assert whole.cut_short is None and whole.posterior.cut_short is None
    stages = dict(whole.clock.ordered())
    assert {"start", "proposals", "settle", "turns", "posterior"} <= set(stages)
    assert stages["start"].evaluations == 16 and stages["settle"].scored > 0


@pytest.mark.slow
def test_estimate_with_a_budget_writes_the_cut_into_the_posterior_file(tmp_path, capsys):
    out, post = tmp_path / "r.csv", tmp_path / "p.json"
    # 0.01 s: shorter than loading the frame, so every run is cut, however fast the machine.
    assert main(["estimate", DEMO, "--particles", "16", "--iterations", "4", "--budget", "0.01",
                 "--out", str(out), "--posterior", str(post)]) == 0
    frame = json.loads(post.read_text())["frames"][0]
    assert frame["cut_short"] == "iterations, settle"
    assert "the budget cut short: iterations, settle" in capsys.readouterr().err
    assert len(out.read_text().splitlines()) == 1 + 2  # header and one row per object


@pytest.mark.slow
def test_bench_profile_prints_every_stage_and_draws_them(tmp_path, capsys):
    png = tmp_path / "profile.png"
    assert main(["bench", "--profile", DEMO, "--scene", "0", "--frame", "0", "--particles", "16", "--iterations",
                 "2", "--png", str(png)]) == 0
    printed = capsys.readouterr().out
    rows = {line.split("|")[1].strip(): line for line in printed.splitlines() if line.startswith("| ")}
    assert {"load", "start", "library", "proposals", "settle", "turns", "posterior", "**all**"} <= set(rows)
    assert int(rows["start"].split("|")[6]) == 16  # the start's projected hypotheses: its particles
    assert "workers' seconds: physics" in printed
    with Image.open(png) as image:
        assert image.size[0] == 900 and image.getcolors(1 << 16) is not None and len(image.getcolors(1 << 16)) > 8


@pytest.mark.slow
def test_bench_profile_of_a_tracked_frame_counts_its_search_and_the_tracker_around_it(tmp_path, capsys):
    """``--tracked-from A``: the scene tracked from A to --frame as ``track`` does; the profile is the last frame's,
    a short search (the carried particles scored as they rest, one step of moves) and its settle, and the
    tracker's own reading of the frame ("load"). An A after the frame is refused before anything runs."""
    from workbench.synth.sequence import make_sequences
    from workbench.track.config import TrackConfig

    make_sequences(tmp_path / "seq", ["touching"], 1, 3, seed=0, width=320, height=240, sensor="kinect-like")
    data = str(tmp_path / "seq")
    assert main(["bench", "--profile", data, "--scene", "0", "--frame", "2", "--tracked-from", "0", "--particles",
                 "40", "--iterations", "3"]) == 0
    printed = capsys.readouterr().out
    assert "frame 0/2 (tracked)" in printed
    rows = {line.split("|")[1].strip(): line.split("|") for line in printed.splitlines() if line.startswith("| ")}
    assert {"load", "start", "proposals", "settle", "**all**"} <= set(rows)
    particles = TrackConfig().particles
    assert int(rows["start"][7]) == particles and int(rows["start"][6]) == 0  # scored as they rest: no physics
    assert int(rows["proposals"][6]) == particles * TrackConfig().iterations
    assert float(rows["load"][2]) > 0
    assert main(["bench", "--profile", data, "--scene", "0", "--frame", "1", "--tracked-from", "2"]) == 2
    assert "--tracked-from" in capsys.readouterr().err


def test_bench_profile_needs_its_frame(capsys):
    assert main(["bench", "--profile", DEMO, "--scene", "0"]) == 2
    assert "--scene S --frame F" in capsys.readouterr().err
