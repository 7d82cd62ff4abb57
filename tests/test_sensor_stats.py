"""The sensor's error statistics (``synth.sensor.stats``) on constructed arrays, and the sensor models of
``synth.sensor.model`` measured by them: fast, no dataset, no OpenGL."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.errors import InputError
from workbench.synth.sensor import stats as st
from workbench.synth.sensor.model import (
    SENSOR_NAMES,
    SensorModel,
    apply_sensor,
    check_sensor,
    correlated_noise,
    quantise,
    sensor_model,
)

K = np.array([[500.0, 0.0, 79.5], [0.0, 500.0, 59.5], [0.0, 0.0, 1.0]])


def test_robust_std_and_tails_of_a_normal_sample_with_outliers():
    rng = np.random.default_rng(0)
    x = rng.normal(0.0, 0.002, 100_000)
    x[:1000] = 0.5  # 1 % gross outliers: the robust std does not see them, the tail share does
    assert st.robust_std(x) == pytest.approx(0.002, rel=0.03)
    assert st.tail_fraction(x) == pytest.approx(0.01 + 0.0027, abs=0.001)
    assert np.isnan(st.robust_std(np.array([])))


def test_incidence_angle_of_a_fronto_parallel_and_a_tilted_plane():
    flat = np.full((120, 160), 1.0)
    a = st.incidence_angle(flat, K)
    assert np.nanmax(np.abs(a[1:-1, 1:-1] - np.arctan(np.hypot(np.mgrid[1:119, 1:159][1] - 79.5,
                                                                np.mgrid[1:119, 1:159][0] - 59.5) / 500))) < 1e-6
    # A plane through the optical axis point turned 60 degrees about the camera's x axis: n = (0, sin, -cos)... its
    # depth along each ray solves n.(z r) = -d.
    n = np.array([0.0, np.sin(np.radians(60)), -np.cos(np.radians(60))])
    v, u = np.mgrid[0:120, 0:160].astype(float)
    rays = np.stack([(u - 79.5) / 500, (v - 59.5) / 500, np.ones_like(u)], axis=-1)
    z = (n @ np.array([0, 0, 1.0])) / (rays @ n)
    a = np.degrees(st.incidence_angle(z, K))
    assert a[60, 80] == pytest.approx(60.0, abs=0.2)
    assert np.isnan(a[0, 0])  # the border has no central difference


def test_correlation_length_of_filtered_noise_and_of_white_noise():
    rng = np.random.default_rng(1)
    mask = np.ones((300, 300), dtype=bool)
    for length in (3.0, 8.0):
        acf = st.autocorrelation(correlated_noise((300, 300), length, rng), mask, 30)
        assert acf[0] == pytest.approx(1.0)
        assert st.correlation_length(acf) == pytest.approx(length, rel=0.1)
    white = st.autocorrelation(rng.normal(size=(300, 300)), mask, 5)
    assert st.correlation_length(white) < 1.0
    assert np.isnan(st.correlation_length(np.ones(5)))  # never falls: no length within the lags


def test_detrend_removes_a_ramp_only_on_the_mask():
    v, u = np.mgrid[0:50, 0:60].astype(float)
    ramp = 0.01 + 1e-4 * u - 2e-4 * v
    mask = np.zeros(ramp.shape, dtype=bool)
    mask[10:40, 5:50] = True
    out = st.detrend(ramp, mask)
    assert np.abs(out).max() < 1e-12


def test_holes_by_edge_grazing_and_elsewhere():
    obs = np.ones((10, 10))
    expected = np.ones((10, 10), dtype=bool)
    edge = np.zeros((10, 10), dtype=bool)
    edge[:, 0] = True
    grazing = np.zeros((10, 10), dtype=bool)
    grazing[:, :2] = True  # the first column is both: it counts as an edge
    obs[:5, 0] = 0  # half the edge
    obs[0, 1] = 0  # a tenth of the grazing pixels
    obs[9, 9] = 0  # one of the 80 elsewhere
    h = st.hole_fractions(obs, expected, edge, grazing)
    assert (h["edge"], h["grazing"], h["elsewhere"]) == pytest.approx((0.5, 0.1, 1 / 80))
    assert (h["n_edge"], h["n_grazing"], h["n_elsewhere"]) == (10, 10, 80)


def test_flying_pixels_lie_between_the_two_sides_and_away_from_both():
    ref = np.full((20, 20), 1.0)
    ref[:, 10:] = 0.8  # a 20 cm step
    edge = st.edge_band(ref, 0.02, 1)
    assert edge[:, 9:11].all() and not edge[:, :9].any()
    obs = ref.copy()
    obs[:10, 9] = 0.9  # in the middle of the step: flying
    obs[10:, 9] = 1.0 + 0.002  # on its own side, noise aside: not flying
    share, n = st.flying_fraction(obs, ref, edge, radius=2, margin=0.005)
    assert n == 40 and share == pytest.approx(10 / 40)


def test_edge_band_ignores_unknown_neighbours():
    ref = np.full((10, 10), 1.0)
    ref[:, 5:] = np.nan  # unknown, not a jump
    assert not st.edge_band(ref, 0.02, 2).any()


def test_local_mean_and_binned_spread():
    x = np.arange(25, dtype=float).reshape(5, 5)
    mask = np.ones((5, 5), dtype=bool)
    assert st.local_mean(x, mask, 1)[2, 2] == pytest.approx(12.0)
    assert st.local_mean(x, mask, 1)[0, 0] == pytest.approx(np.mean([0, 1, 5, 6]))
    rng = np.random.default_rng(2)
    z = rng.uniform(0.5, 1.5, 50_000)
    r = rng.normal(size=z.size) * 0.001 * z**2
    bins = st.binned_spread(r, z, np.array([0.5, 0.7, 1.3, 1.5]))
    assert bins[0]["robust_std"] == pytest.approx(0.001 * 0.6**2, rel=0.1)
    assert bins[2]["robust_std"] == pytest.approx(0.001 * 1.4**2, rel=0.1)
    assert st.relative_difference(1.1, 1.0) == pytest.approx(0.1)


def test_kinect_like_stays_the_default_model_and_ideal_changes_nothing():
    assert sensor_model("kinect-like") == SensorModel()
    clean = np.full((40, 50), 0.9)
    clean[:, 25:] = 0.0
    assert np.array_equal(apply_sensor(clean, np.random.default_rng(0), sensor_model("ideal"), K),
                          clean.astype(np.float32))
    check_sensor("xtion")
    with pytest.raises(InputError, match="choose from"):
        check_sensor("sonar")
    assert set(SENSOR_NAMES) == {"ideal", "kinect-like", "xtion"}


def test_disparity_steps_grow_with_the_square_of_depth():
    model = SensorModel(disparity_quantum=0.003)
    for z in (0.5, 1.0, 2.0):
        values = np.unique(quantise(np.linspace(z - 0.02, z + 0.02, 4001), model))
        assert np.median(np.diff(values)) == pytest.approx(0.003 * z**2, rel=0.05)


def test_xtion_model_shows_its_measured_statistics_on_a_plane():
    """A flat wall at 1 m with a box in front: the fast noise's std and length, holes and flying pixels come out as
    the model's parameters say (its numbers are measured on the real frames: ``benchmarks/sensor_stats.py``)."""
    model = sensor_model("xtion")
    clean = np.full((240, 320), 1.0)
    clean[80:160, 100:200] = 0.8
    k = np.array([[525.0, 0.0, 159.5], [0.0, 525.0, 119.5], [0.0, 0.0, 1.0]])
    obs = apply_sensor(clean, np.random.default_rng(3), model, k).astype(np.float64)
    wall = (clean == 1.0) & (obs > 0)
    wall[70:170, 90:210] = False
    res = obs - clean
    fast = res - np.nan_to_num(st.local_mean(res, wall, 8))
    assert st.robust_std(fast[wall]) == pytest.approx(model.sigma_quad, rel=0.25)
    length_mrad = st.correlation_length(st.autocorrelation(np.where(wall, fast, 0.0), wall, 20)) / 525 * 1e3
    assert length_mrad == pytest.approx(model.noise_corr_mrad, rel=0.35)
    edge = st.edge_band(clean, 0.02, 2)
    assert np.mean(obs[edge] == 0) == pytest.approx(model.edge_drop, abs=0.1)
    assert np.mean(obs[~edge] == 0) == pytest.approx(model.random_drop, abs=0.01)
    share, _ = st.flying_fraction(obs, clean, edge, 3, 0.005)
    assert 0.3 * model.flying < share < 2 * model.flying
    with pytest.raises(ValueError, match="intrinsics"):
        apply_sensor(clean, np.random.default_rng(0), model)


def test_make_scenes_takes_the_sensor_by_name_and_keeps_kinect_like_by_default():
    from workbench.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["make-scenes", "out"]).sensor == "xtion"  # new sets: the sensor measured on real frames
    assert parser.parse_args(["make-scenes", "out", "--sensor", "xtion"]).sensor == "xtion"
    with pytest.raises(SystemExit):
        parser.parse_args(["make-scenes", "out", "--sensor", "sonar"])
