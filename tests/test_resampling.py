import numpy as np

from workbench.inference.smc.resampling import ess, log_sum_exp, normalised_weights, systematic_resample, temper_to_ess


def test_log_sum_exp_survives_huge_log_weights():
    lw = np.array([-1e6, -1e6 + np.log(3.0)])
    assert np.isclose(log_sum_exp(lw), -1e6 + np.log(4.0))
    assert np.allclose(normalised_weights(lw), [0.25, 0.75])


def test_minus_inf_particles_are_never_drawn():
    lw = np.array([0.0, -np.inf, 0.0, -np.inf])
    idx = systematic_resample(lw, np.random.default_rng(0), 1000)
    assert set(idx.tolist()) == {0, 2}


def test_all_failed_particles_give_uniform_weights():
    assert np.allclose(normalised_weights(np.full(4, -np.inf)), 0.25)


def test_systematic_resampling_matches_weights():
    w = np.array([0.1, 0.2, 0.7])
    idx = systematic_resample(np.log(w), np.random.default_rng(1), 1000)
    counts = np.bincount(idx, minlength=3) / 1000
    assert np.allclose(counts, w, atol=1e-3 + 1e-9)


def test_systematic_resampling_can_change_the_particle_count():
    idx = systematic_resample(np.zeros(10), np.random.default_rng(2), 25)
    assert idx.shape == (25,) and idx.min() >= 0 and idx.max() <= 9


def test_ess_bounds():
    assert np.isclose(ess(np.zeros(50)), 50.0)
    assert np.isclose(ess(np.array([0.0] + [-1e9] * 49)), 1.0)


def test_tempering_reaches_the_target_ess():
    loglik = np.random.default_rng(3).normal(scale=500.0, size=400)  # raw weights: one particle takes all
    beta = temper_to_ess(loglik, 0.25)
    assert 0 < beta < 1
    assert np.isclose(ess(beta * loglik), 100.0, rtol=0.01)


def test_tempering_keeps_beta_one_when_weights_are_already_flat():
    assert temper_to_ess(np.linspace(0, 0.1, 100), 0.5) == 1.0
