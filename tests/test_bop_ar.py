"""BOP 2019's average recall in `workbench score` (``score.ar``): MSSD and MSPD up to the symmetries, and each
object's share of their thresholds, on cases computed by hand."""

import numpy as np
import pytest

from workbench.geometry import make_pose, rot_z
from workbench.score import ar
from workbench.score.metrics import mssd

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
# A flat cross of four points 5 cm from its centre: its diameter is 0.1 m, and a half turn about z maps it onto itself.
CROSS = np.array([[0.05, 0.0, 0.0], [-0.05, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, -0.05, 0.0]])
AT_1M = make_pose(np.eye(3), [0.0, 0.0, 1.0])


def test_an_estimate_at_the_truth_recalls_every_threshold():
    assert ar.mspd(AT_1M, AT_1M, CROSS, K) == 0.0
    assert ar.ar_mssd(mssd(AT_1M, AT_1M, CROSS), 0.1) == 1.0
    assert ar.ar_mspd(ar.mspd(AT_1M, AT_1M, CROSS, K), 640) == 1.0


def test_a_known_shift_recalls_the_thresholds_it_is_under():
    shifted = make_pose(np.eye(3), [0.012, 0.0, 1.0])  # 1.2 cm along x, 1 m away: 6 px at f = 500 px
    assert mssd(AT_1M, shifted, CROSS) == pytest.approx(0.012)
    assert ar.mspd(AT_1M, shifted, CROSS, K) == pytest.approx(6.0)
    # MSSD thresholds 0.5, 1.0, ..., 5.0 cm of a 10 cm object: 1.2 cm is under 8 of them
    assert ar.ar_mssd(0.012, 0.1) == pytest.approx(0.8)
    # MSPD thresholds 5, 10, ..., 50 px at 640 px wide: 6 px is under 9; at 320 px wide (2.5, 5, 7.5, ...) under 8
    assert ar.ar_mspd(6.0, 640) == pytest.approx(0.9)
    assert ar.ar_mspd(6.0, 320) == pytest.approx(0.8)
    # BOP's test is strict: an error equal to a threshold is not under it
    assert ar.recall(5.0, np.array([5.0, 10.0])) == 0.5


def test_a_turn_the_symmetries_allow_is_no_error_and_a_missing_estimate_recalls_nothing():
    turned = make_pose(rot_z(np.pi), [0.0, 0.0, 1.0])
    half_turn = np.stack([np.eye(4), make_pose(rot_z(np.pi), [0.0, 0.0, 0.0])])
    assert mssd(AT_1M, turned, CROSS) == pytest.approx(0.1)  # each point to its opposite
    assert mssd(AT_1M, turned, CROSS, half_turn) == pytest.approx(0.0, abs=1e-12)
    assert ar.mspd(AT_1M, turned, CROSS, K, half_turn) == pytest.approx(0.0, abs=1e-9)
    assert ar.recall(np.nan, ar.MSSD_FRACTIONS) == 0.0 and ar.recall(np.inf, ar.MSPD_PIXELS) == 0.0


def test_a_continuous_symmetry_is_sampled_as_bop_toolkit_samples_it():
    steps = ar.continuous_steps()
    assert steps == 315  # ceil(pi / 0.01): a rim point moves at most 1 % of the diameter between samples
    assert np.pi * 0.1 / steps <= 0.01 * 0.1
