"""The filter core, the particle set and the move registry, on a toy problem with a made-up likelihood (tests/toy.py):
no physics, no rendering, exact and seeded. The fast tier: `pytest -m "not slow"`."""

import os
import re
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from toy import ToyEvaluator, toy_problem, toy_target

from workbench.errors import InputError
from workbench.evaluation import Evaluation
from workbench.geometry import make_pose
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator
from workbench.inference.search.moves.context import MoveContext
from workbench.inference.search.moves.registry import MOVES, REGISTRY, MoveKind, MoveMix
from workbench.inference.smc.filter import ParticleFilter, Proposed, Settled, Started
from workbench.inference.smc.particles import Sigma
from workbench.inference.smc.particleset import ParticleSet

PAPER = EstimatorConfig(proposals="paper", particles=120, iterations=25, state="xyzyaw", seed=4)


@pytest.fixture(scope="module")
def toy():
    problem = toy_problem()
    return problem, toy_target(problem)


def _run(toy, config, steps):
    problem, target = toy
    estimator = Estimator(problem, config, ToyEvaluator(problem, target))
    for _ in range(steps):
        estimator.step()
    return estimator


# ------------------------------------------------------------------------------------------------ the filter


@pytest.mark.parametrize("method", ["pipf", "mcpf"])
def test_the_paper_filter_finds_the_target_and_the_estimate_never_gets_worse(toy, method):
    problem, target = toy
    estimator = _run(toy, replace(PAPER, method=method), 25)
    best = estimator.settle()
    assert np.max(np.linalg.norm(best[:, :3, 3] - target[:, :3, 3], axis=-1)) < 0.02
    trace = [r.best_loglik for r in estimator.history]
    assert np.all(np.diff(trace) >= 0) and trace[-1] > trace[0]
    assert estimator.estimate_loglik >= estimator.particles.loglik.max()
    assert len(estimator.particles) == PAPER.particles and estimator.evaluations == 25 * PAPER.particles


@pytest.mark.parametrize("method", ["pipf", "mcpf"])
def test_seeded_runs_are_bit_identical_and_seeds_differ(toy, method):
    a, b = (_run(toy, replace(PAPER, method=method), 4) for _ in range(2))
    other = _run(toy, replace(PAPER, method=method, seed=5), 4)
    for name, array in a.particles.arrays().items():
        assert np.array_equal(array, getattr(b.particles, name)), name
    assert a.rng.bit_generator.state == b.rng.bit_generator.state
    assert not np.array_equal(a.particles.projected, other.particles.projected)


class _FixedSearch:
    """A search whose every proposal is its parent with object 0 moved by ``dx`` (m): the likelihood of each
    proposal against its parent's is known, so the Metropolis-Hastings step can be checked exactly."""

    def __init__(self, start: np.ndarray, dx: float):
        self.start_scenes, self.dx = start, dx

    def start(self, filt):
        return Started(self.start_scenes.copy(), np.full(len(self.start_scenes), int(MoveKind.START), np.int8))

    def propose(self, filt, parents):
        out = parents.copy()
        out[:, 0, 0, 3] += self.dx
        n = len(parents)
        return Proposed(out, np.zeros(n), np.full(n, int(MoveKind.JOINT), np.int8), filt.evaluate(out), 0.0)

    def after_step(self, filt):
        return ()

    def finish(self, filt):
        return Settled(filt.estimated_scene.copy(), filt.estimate_loglik)


@pytest.mark.parametrize("dx,accepted", [(0.01, 1.0), (-0.01, 0.0)])
def test_mcpf_accepts_every_better_proposal_and_keeps_the_parents_of_far_worse_ones(toy, dx, accepted):
    problem, target = toy
    start = np.repeat(target[None], 50, axis=0)
    start[:, 0, 0, 3] -= 0.05 + np.linspace(0, 0.004, 50)  # object 0 5-5.4 cm short of its place along x
    config = replace(PAPER, method="mcpf", particles=50)
    filt = ParticleFilter(problem, config, ToyEvaluator(problem, target, sigma_m=0.002), _FixedSearch(start, dx))
    filt.step()
    before = filt.particles.copy()
    report = filt.step()
    assert report.accept_rate == accepted
    # Each particle is now its resampled parent (one of ``before``), moved by dx where the proposal was accepted.
    x_now, x_before = filt.particles.projected[:, 0, 0, 3], before.projected[:, 0, 0, 3]
    moved = np.isclose(x_now[:, None] - dx, x_before[None, :]).any(axis=1)
    assert moved.all() if accepted else not moved.any()
    assert report.moves == {"joint": {"proposed": 50.0, "accepted": 50.0 * accepted}}


def test_a_settings_change_resizes_the_set_at_the_next_resampling_and_keeps_the_seed(toy):
    estimator = _run(toy, PAPER, 2)
    estimator.set_config(replace(PAPER, particles=30, seed=99))
    estimator.step()
    assert len(estimator.particles) == 30 and estimator.config.seed == PAPER.seed


# ---------------------------------------------------------------------------------------------- particle set


def _set(n, K=2, offset=0.0):
    T = np.repeat(np.eye(4)[None, None], n, axis=0).repeat(K, axis=1)
    T[:, :, 0, 3] = np.arange(n)[:, None] + offset
    return ParticleSet(T, T + 1.0, np.arange(n) + offset, np.arange(n, dtype=np.int8), np.full(n, 3, np.int8))


def test_particle_set_indexing_copyto_put_and_round_trip():
    a, b = _set(5), _set(5, offset=10.0)
    picked = a[np.array([4, 4, 0])]
    assert picked.loglik.tolist() == [4, 4, 0] and len(picked) == 3
    picked.loglik[0] = -1.0
    assert a.loglik[4] == 4  # rows are copies
    where = np.array([True, False, True, False, False])
    a.copyto(b, where)
    assert a.loglik.tolist() == [10, 1, 12, 3, 4] and np.array_equal(a.hypotheses[2], b.hypotheses[2])
    a.put(np.array([1]), b[np.array([3])])
    assert a.loglik[1] == 13 and a.status[1] == b.status[3]
    again = ParticleSet.from_arrays({k: v.tolist() for k, v in a.arrays().items()})
    for name, array in a.arrays().items():
        assert np.array_equal(getattr(again, name), array) and getattr(again, name).dtype == array.dtype


def test_evaluations_concatenate_and_interleave_as_one_batch():
    a = Evaluation(np.zeros((2, 1, 4, 4)), np.array([1.0, 2.0]), np.array([0, 0], np.int8), np.zeros(2),
                   {"projection": 1.0, "render": 0.0, "likelihood": 0.5})
    b = Evaluation(np.ones((1, 1, 4, 4)), np.array([3.0]), np.array([4], np.int8), np.zeros(1),
                   {"projection": 2.0, "render": 1.0, "likelihood": 0.5})
    both = Evaluation.concatenate([a, b])
    assert both.loglik.tolist() == [1, 2, 3] and both.timings == {"projection": 3.0, "render": 1.0, "likelihood": 1.0}
    mixed = Evaluation.interleave(np.array([True, False, True]), a, b)
    assert mixed.loglik.tolist() == [1, 3, 2] and mixed.status.tolist() == [0, 4, 0]
    assert mixed.status.dtype == np.int8 and mixed.projected[1].sum() == 16


# -------------------------------------------------------------------------------------------- move registry


def test_every_registered_kind_has_its_own_code_and_is_drawn_by_its_share():
    assert len({m.code for m in MOVES}) == len(MOVES) and set(REGISTRY) == {m.code for m in MOVES}
    assert {MoveKind(m.code).label for m in MOVES} == {m.name for m in MOVES}
    mix = MoveMix()
    drawn = mix.draw(np.random.default_rng(0), 20_000)
    shares = mix.as_array() / mix.as_array().sum()
    for move, share in zip(MOVES, shares):
        assert abs(np.mean(drawn == move.code) - share) < 0.01, move.name
    assert set(MoveMix.paper().draw(np.random.default_rng(0), 100).tolist()) == {int(MoveKind.JOINT)}


def test_the_reduced_state_draws_no_kind_that_tilts_and_saved_mixes_load_as_they_ran():
    tilting = {m.code for m in MOVES if m.tilts}
    assert tilting and not set(MoveMix().for_state("xyzyaw").draw(np.random.default_rng(1), 5000)) & tilting
    saved = {"joint": 0.5, "single": 0.5}  # a mix saved before the other kinds existed
    assert MoveMix.from_dict(saved).as_dict() == {m.name: saved.get(m.name, 0.0) for m in MOVES}
    with pytest.raises(InputError, match="unknown move kinds"):
        MoveMix(wiggle=1.0)
    with pytest.raises(InputError, match=">= 0"):
        MoveMix(joint=-1.0).validate()


@pytest.mark.parametrize("name", ["joint", "single", "turn", "relocate"])
def test_moves_that_need_no_observation_are_valid_seeded_and_move_something(toy, name):
    problem, target = toy
    K = problem.n_objects
    parents = np.repeat(target[None], 16, axis=0)
    ctx = MoveContext(problem, None, None, Sigma(), "6dof", "mcpf", choose=np.ones(K), scales=np.ones(K))
    move = next(m for m in MOVES if m.name == name)
    a, b = (move.propose(np.random.default_rng(2), parents, ctx) for _ in range(2))
    assert np.array_equal(a.hypotheses, b.hypotheses) and a.log_q_ratio.shape == (16,)
    R = a.hypotheses[..., :3, :3]
    assert np.allclose(np.swapaxes(R, -1, -2) @ R, np.eye(3), atol=1e-9)
    assert not np.array_equal(a.hypotheses, parents)
    assert np.array_equal(make_pose(np.eye(3), [0, 0, 0])[3], a.hypotheses[0, 0, 3])


def test_the_readme_example_kind_is_one_module_and_one_registry_line(tmp_path):
    """docs/design.md's "Adding a move kind", done to a copy of the package: the module as printed there, its name
    added to registry.py's import and its line to MOVES. The kind then has its code, its default share and proposes."""
    root = Path(__file__).resolve().parents[1]
    example = re.search(r"```python\n# workbench/inference/search/moves/spin.py\n(.*?)```",
                        (root / "docs" / "design.md").read_text(), re.S)
    package = tmp_path / "workbench"
    shutil.copytree(root / "workbench", package, ignore=shutil.ignore_patterns("__pycache__"))
    (package / "inference" / "search" / "moves" / "spin.py").write_text(example.group(1))
    moves = package / "inference" / "search" / "moves" / "registry.py"
    text = moves.read_text()
    for old, new in (("from workbench.inference.search.moves import kinds\n",
                      "from workbench.inference.search.moves import kinds, spin\n"),
                     ("    kinds.Relocate(),\n)", "    kinds.Relocate(),\n    spin.Spin(),\n)")):
        assert old in text
        text = text.replace(old, new)
    moves.write_text(text)
    check = """
import numpy as np
from toy import toy_problem, toy_target
from workbench.inference.search.moves.context import MoveContext
from workbench.inference.search.moves.registry import REGISTRY, MoveKind, MoveMix
from workbench.inference.smc.particles import Sigma
assert MoveKind.SPIN == 13 and MoveKind(13).label == "spin" and MoveMix().as_dict()["spin"] == 0.05
problem = toy_problem()
parents = np.repeat(toy_target(problem)[None], 8, axis=0)
ctx = MoveContext(problem, None, None, Sigma(), "6dof", "pipf", choose=np.ones(2), scales=np.ones(2))
p = REGISTRY[13].propose(np.random.default_rng(0), parents, ctx)
assert p.hypotheses.shape == parents.shape and not np.array_equal(p.hypotheses, parents)
print("spin ok")
"""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(root / "tests")])}
    done = subprocess.run([sys.executable, "-c", check], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert done.stdout.strip() == "spin ok", done.stderr
