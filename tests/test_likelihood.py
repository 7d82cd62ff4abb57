from dataclasses import replace

import numpy as np
import pytest

from workbench.errors import InputError
from workbench.render.likelihood import (
    LikelihoodConfig,
    clutter_segments,
    drawn_over_loglik,
    pixel_loglik,
    scene_loglik,
)


def _scene():
    observed = np.full((20, 30), 1.0, np.float32)
    observed[5:10, 5:10] = 0.9  # an object 10 cm in front of the table
    observed[0, :] = 0.0  # a row of holes
    background = np.full((20, 30), 1.0, np.float32)
    right = np.zeros((20, 30), np.float32)
    right[5:10, 5:10] = 0.9
    wrong = np.zeros((20, 30), np.float32)
    wrong[12:17, 20:25] = 0.9
    return observed, background, np.stack([right, wrong])


@pytest.mark.parametrize("model", ["robust", "ssd"])
def test_the_true_scene_is_more_likely(model):
    observed, background, rendered = _scene()
    ll = scene_loglik(observed, background, rendered, LikelihoodConfig(model=model))
    assert ll[0] > ll[1]


@pytest.mark.parametrize("model", ["robust", "ssd"])
@pytest.mark.parametrize("floor", [None, 2.0])
def test_sparse_scene_loglik_equals_the_dense_sum(model, floor):
    rng = np.random.default_rng(0)
    observed = rng.uniform(0.5, 1.0, (20, 30)).astype(np.float32)
    observed[2:8, 3:12] = 0.9  # pieces of clutter, for the floor
    observed[10:18, 15:28] = 0.8
    observed[rng.random((20, 30)) < 0.1] = 0.0
    background = np.where(rng.random((20, 30)) < 0.8, 1.0, 0.0).astype(np.float32)
    rendered = np.where(rng.random((5, 20, 30)) < 0.3, rng.uniform(0.5, 1.0, (5, 20, 30)), 0.0).astype(np.float32)
    cfg = LikelihoodConfig(model=model, clutter_floor=floor)
    dense = pixel_loglik(observed, background, rendered, cfg).sum(axis=(1, 2), dtype=np.float64)
    assert np.allclose(scene_loglik(observed, background, rendered, cfg), dense, rtol=1e-5)


def test_pixels_without_a_reading_are_ignored():
    observed, background, rendered = _scene()
    rendered[:, 0, :] = 5.0  # whatever is drawn where the sensor saw nothing must not matter
    ll = pixel_loglik(observed, background, rendered, LikelihoodConfig())
    assert np.all(ll[:, 0, :] == 0)


def test_robust_model_bounds_the_cost_of_an_outlier_pixel():
    cfg = LikelihoodConfig()
    observed = np.array([[1.0, 1.0]], np.float32)
    table = np.zeros_like(observed)
    near = pixel_loglik(observed, table, np.array([[[1.0, 1.5]]], np.float32), cfg)
    far = pixel_loglik(observed, table, np.array([[[1.0, 50.0]]], np.float32), cfg)
    assert np.isclose(near[0, 0, 1], far[0, 0, 1])  # both are pure outliers
    assert near[0, 0, 0] > near[0, 0, 1]


def test_bad_settings_are_named():
    with pytest.raises(InputError, match="sigma"):
        LikelihoodConfig(sigma=-1.0).validate()
    with pytest.raises(InputError, match="model"):
        LikelihoodConfig(model="l1").validate()
    with pytest.raises(InputError, match="free_space"):
        LikelihoodConfig(free_space=0.0).validate()
    with pytest.raises(InputError, match="clutter_floor"):
        LikelihoodConfig(clutter_floor=float("nan")).validate()


def test_a_free_space_violation_costs_more_than_an_occluding_reading():
    """A reading 10 cm behind the predicted surface (the sensor saw through it) against one 10 cm in front (an
    unmodelled occluder): the symmetric mixture scores them alike, the free-space term lowers the first."""
    observed = np.array([[1.1, 0.9]], np.float32)
    predicted = np.array([[[1.0, 1.0]]], np.float32)
    table = np.zeros_like(observed)
    symmetric = pixel_loglik(observed, table, predicted, LikelihoodConfig(free_space=1.0))[0, 0]
    assert np.isclose(symmetric[0], symmetric[1])
    free = pixel_loglik(observed, table, predicted, LikelihoodConfig(free_space=0.1))[0, 0]
    assert free[1] == pytest.approx(symmetric[1])
    assert free[0] == pytest.approx(symmetric[0] + np.log(0.1), abs=1e-3)
    # The same in a scene: an object drawn over a hole in it (the table seen through it) loses, one drawn where
    # something unmodelled stands in front of it does not.
    observed, background, rendered = _scene()
    cfg = LikelihoodConfig(free_space=0.1)
    through = rendered[:1].copy()
    through[0, 12:17, 5:10] = 0.95  # over the bare table: the sensor sees the table behind it
    base = scene_loglik(observed, background, rendered[:1], cfg)[0]
    assert scene_loglik(observed, background, through, cfg)[0] < \
        base + (scene_loglik(observed, background, through, LikelihoodConfig())[0]
                - scene_loglik(observed, background, rendered[:1], LikelihoodConfig())[0])


def test_an_object_gains_on_unmodelled_clutter_only_by_explaining_all_of_it():
    """A 10 cm distractor nobody modelled, and hypotheses: nothing drawn on it; an object whose top fits all of it
    within 5 mm; one that fits a third of it (a thin object laid on part of a box); one drawn behind it, hidden by
    it (the distractor shows beside it too). Without the clutter floor, covering part of the distractor beats
    leaving it (an unexplained reading is an outlier). With it, the bare distractor scores the floor and a piece
    the objects claim part of loses it: only explaining all of it gains, and an object hidden behind clutter costs
    nothing there."""
    observed = np.full((30, 30), 1.0, np.float32)
    observed[5:15, 5:15] = 0.9  # the distractor
    background = np.full((30, 30), 1.0, np.float32)
    rendered = np.zeros((4, 30, 30), np.float32)
    rendered[1, 5:15, 5:15] = 0.905
    rendered[2, 5:8, 5:15] = 0.905
    rendered[3, 5:15, 5:9] = 0.95  # behind 40 readings of its 100
    plain_cfg, cfg = LikelihoodConfig(clutter_floor=None), LikelihoodConfig(clutter_floor=2.0)
    plain = scene_loglik(observed, background, rendered, plain_cfg)
    floor = scene_loglik(observed, background, rendered, cfg)
    assert plain[2] > plain[0]
    assert floor[2] < floor[0] < floor[1]
    assert floor[3] == pytest.approx(floor[0])
    assert floor[0] > plain[0]  # the distractor's pixels now score the floor, not the outlier term
    pixels, plain_pixels = (pixel_loglik(observed, background, rendered, c) for c in (cfg, plain_cfg))
    assert np.allclose(pixels[0, 5:15, 5:15], 2.0)
    assert np.allclose(pixels[2, 8:15, 5:15], plain_pixels[2, 8:15, 5:15])  # claimed: no floor on the rest
    assert np.allclose(pixels[:, 20:], plain_pixels[:, 20:])  # the bare table, as before


def test_an_object_gains_nothing_by_fitting_a_few_readings_of_a_large_piece_of_clutter():
    """A large flat piece of unmodelled clutter (a sheet 1.5 cm above the table) and a thin object's hypotheses:
    laid flat on a corner of it, claiming fewer than CLAIM_SHARE of its readings (the piece stays clutter); laid
    there but 5 cm higher, so the sensor sees through it; nothing drawn. Fitting part of clutter gains nothing over
    what the bare table scores there, while the free-space violation still costs: the object's own readings elsewhere
    decide."""
    observed = np.full((40, 40), 1.0, np.float32)
    observed[2:38, 2:38] = 0.985  # the sheet: 1296 readings
    background = np.full((40, 40), 1.0, np.float32)
    rendered = np.zeros((3, 40, 40), np.float32)
    rendered[0, 5:8, 5:30] = 0.985  # 75 readings: under a tenth of the piece
    rendered[1, 5:8, 5:30] = 0.935
    cfg = LikelihoodConfig(clutter_floor=2.0)
    ll = scene_loglik(observed, background, rendered, cfg)
    assert ll[0] == pytest.approx(ll[2])
    assert ll[1] < ll[2] - 75 * 3
    pixels = pixel_loglik(observed, background, rendered, cfg)
    assert np.allclose(pixels[0], pixels[2])  # what the bare table scores there (above the floor), though it fits


def test_an_object_behind_its_own_visible_face_gets_no_clutter_floor():
    """A box's face seen 10 cm in front of the table (100 readings), and the box drawn: at its face; 4 cm behind it
    but still touching its top row (it claims 20 readings, the piece keeps no floor); 8 cm behind it, over 80 of its
    readings and claiming none. The readings the box lies behind are its own face, not clutter in front of it:
    they keep no floor, so backing further away from what the sensor sees never gains (it gained 5.4 a reading,
    a basin that held estimates 6-10 cm behind their faces). An object hidden behind clutter that also shows
    beside it still costs nothing there (``test_an_object_gains_on_unmodelled_clutter_only_...``)."""
    observed = np.full((30, 30), 1.0, np.float32)
    observed[5:15, 5:15] = 0.9  # the face
    background = np.full((30, 30), 1.0, np.float32)
    rendered = np.zeros((4, 30, 30), np.float32)
    rendered[0, 5:15, 5:15] = 0.9
    rendered[1, 5:15, 5:15] = 0.94
    rendered[1, 5:7, 5:15] = 0.9  # its top edge still meets the readings
    rendered[2, 7:15, 5:15] = 0.98
    cfg = LikelihoodConfig(clutter_floor=2.0)
    at_face, nearer, farther, bare = scene_loglik(observed, background, rendered, cfg)
    assert at_face > nearer >= farther
    pixels = pixel_loglik(observed, background, rendered, cfg)
    assert np.allclose(pixels[3, 5:15, 5:15], 2.0)  # nothing drawn there: the face is clutter
    plain = pixel_loglik(observed, background, rendered, replace(cfg, clutter_floor=None))
    assert np.allclose(pixels[2], plain[2])  # the box behind it: its readings outliers, as without the floor


def test_drawing_over_a_base_scores_as_the_composite():
    """``drawn_over_loglik`` of objects drawn over a base scene equals the composite's ``scene_loglik`` less the
    base's, with the clutter floor's claims and cover counted over both."""
    rng = np.random.default_rng(3)
    observed = np.full((24, 32), 1.0, np.float32)
    observed[3:12, 4:14] = 0.9  # pieces of clutter
    observed[14:22, 16:30] = 0.85
    observed += rng.normal(0.0, 0.002, observed.shape).astype(np.float32)
    observed[rng.random(observed.shape) < 0.05] = 0.0
    background = np.full((24, 32), 1.0, np.float32)
    base = np.zeros((24, 32), np.float32)
    base[4:10, 4:9] = 0.95  # behind part of the first piece
    own = np.zeros((6, 24, 32), np.float32)
    own[0, 3:12, 4:14] = 0.97  # behind all of the first piece
    own[1, 14:22, 16:30] = 0.85  # the second piece explained
    own[2, 14:22, 16:23] = 0.9  # behind half of the second
    own[3, 2:6, 2:20] = 0.92  # over part of the first, partly claiming it
    own[4] = np.where(rng.random(observed.shape) < 0.3, rng.uniform(0.8, 1.0, observed.shape), 0.0)
    cfg = LikelihoodConfig(clutter_floor=2.0)
    composite = np.where((own > 0) & ((base == 0) | (own < base)), own, base[None])
    expected = scene_loglik(observed, background, composite, cfg) - scene_loglik(observed, background, base[None],
                                                                                  cfg)[0]
    assert np.allclose(drawn_over_loglik(observed, background, base, own, cfg), expected, atol=1e-3)


def test_clutter_pieces_are_joined_readings_in_front_of_the_table():
    """Two boxes standing on the table, a step of 5 cm between two halves of one, and a speck of noise: three
    pieces (the step splits one); the table and the speck are not clutter."""
    observed = np.full((40, 40), 1.0, np.float32)
    observed[5:15, 5:15] = 0.9
    observed[5:15, 15:25] = 0.85  # 5 cm nearer than its neighbour: another piece
    observed[25:35, 30:40] = 0.95
    observed[30, 10] = 0.8  # speckle
    observed[0, :] = 0.0
    pieces = clutter_segments(observed, np.full((40, 40), 1.0, np.float32), LikelihoodConfig())
    assert len(np.unique(pieces[pieces >= 0])) == 3
    assert pieces[30, 10] == -1 and pieces[20, 20] == -1
    assert pieces[10, 10] != pieces[10, 20] and (pieces[5:15, 5:15] == pieces[10, 10]).all()
