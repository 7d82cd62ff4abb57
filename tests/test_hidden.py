"""A hidden object's region (inference.answer.hidden, posterior.hidden): where an object the sensor sees none of can
be as well. The grid and the probabilities are in the fast tier; the generated occluded frame runs the real renderer
and likelihood, and the estimator's settling and posterior sweep."""

import json
from types import SimpleNamespace

import numpy as np
import pytest

from workbench.geometry import invert_pose
from workbench.inference.answer.hidden import REACH, SPACING, TOLERANCE_CELLS, HidingRegion, level_offsets
from workbench.inference.answer.posterior import Mode, ObjectPosterior, Posterior, hidden, probabilities
from workbench.score.metrics import RIGHT_CM
from workbench.sessions.answer import parse_posterior, posterior_json


def test_the_grid_reaches_every_point_of_its_disc_within_the_right_pose_tolerance():
    offsets = level_offsets()
    assert np.array_equal(offsets[0], [0.0, 0.0]) and np.all(np.linalg.norm(offsets, axis=1) <= REACH + 1e-9)
    rng = np.random.default_rng(0)
    r, a = (REACH - SPACING) * np.sqrt(rng.random(2000)), 2 * np.pi * rng.random(2000)
    points = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    nearest = np.linalg.norm(points[:, None] - offsets[None], axis=-1).min(axis=1)
    assert nearest.max() < RIGHT_CM / 100  # a truth anywhere inside is "right" for some place, heading aside


def _hidden_mug():
    modes = [Mode(np.eye(4), 0.0, 0.0, 0.6, "the estimate"), Mode(np.eye(4), -6.0, -6.0, 0.4, "turned over")]
    o = ObjectPosterior(0, modes, 0.002, seen_through=1.0, elsewhere=0.99)
    places = np.array([[0.3, 0.1, 0.04], [0.325, 0.1, 0.04], [0.35, 0.1, 0.04], [0.35, 0.125, 0.04]])
    return hidden(o, places, np.array([0.0, 0.0, -1.0, -30.0]), 15.0)


def test_a_hidden_object_is_elsewhere_than_its_modes_as_far_as_the_rest_of_its_region_holds():
    o = _hidden_mug()
    p = probabilities(np.array([0.0, 0.0, -1.0, -30.0]), 15.0)
    assert np.allclose(o.hiding.probabilities, p) and np.isclose(o.hiding.probabilities.sum(), 1.0)
    assert [m.probability for m in o.modes] == [0.6, 0.4]  # given its place, as every object's given it was found
    # Its place holds a grid cell of the region; the truth is right within 2 cm of it, a disc of about two cells.
    assert 1.9 < TOLERANCE_CELLS < 2.1 and np.isclose(o.hiding.estimate_share, p[0] * TOLERANCE_CELLS)
    assert np.isclose(o.elsewhere, 1.0 - o.hiding.estimate_share) and o.seen_through == 1.0
    assert np.isclose(o.hiding.extent_m, np.hypot(0.05, 0.025))
    line = Posterior([o]).summary(SimpleNamespace(models=[SimpleNamespace(name="mug", obj_id=1)]))
    assert line == ("1 of 1 objects uncertain: mug (hidden: one of 4 places up to 6 cm apart, "
                    f"p = {o.hiding.estimate_share:.2f} where estimated)")
    alone = hidden(ObjectPosterior(0, o.modes, 0.002), o.hiding.places[:1], np.zeros(1), 15.0)
    assert alone.hiding.estimate_share == 1.0 and alone.elsewhere == 0.0  # a region of one place: it is there


def test_a_hidden_objects_result_rows_are_given_its_place_and_its_record_holds_the_region():
    from workbench.io.results import posterior_rows

    o = _hidden_mug()
    T_cam_world = np.eye(4)
    T_cam_world[2, 3] = 0.5
    problem = SimpleNamespace(models=[SimpleNamespace(name="mug", obj_id=1)],
                              camera=SimpleNamespace(T_cam_world=T_cam_world))
    rows = posterior_rows(SimpleNamespace(scene_id=0, im_id=0), problem, Posterior([o]), 1.0)
    assert [r.score for r in rows] == pytest.approx([0.6, 0.4])  # as `workbench score` groups an object's rows
    hiding = rows[0].posterior["hiding"]
    assert np.allclose(hiding["places_mm"], (o.hiding.places + [0.0, 0.0, 0.5]) * 1000.0)  # camera frame, mm
    assert hiding["probabilities"] == pytest.approx(o.hiding.probabilities.tolist(), abs=1e-6)
    assert hiding["gaps"] == pytest.approx(o.hiding.gaps.tolist(), abs=1e-3)


def test_a_hidden_objects_region_is_saved_and_read_back_and_a_damaged_one_is_refused():
    o = _hidden_mug()
    sure = ObjectPosterior(1, [Mode(np.eye(4), 0.0, 0.0, 1.0, "the estimate")], 0.001)
    doc = json.loads(json.dumps(posterior_json(Posterior([o, sure]))))
    back = parse_posterior(doc, 2).objects
    assert back[1].hiding is None
    assert np.array_equal(back[0].hiding.places, o.hiding.places)
    assert np.array_equal(back[0].hiding.probabilities, o.hiding.probabilities)
    assert np.array_equal(back[0].hiding.gaps, o.hiding.gaps)
    doc["objects"][0]["hiding"]["probabilities"][1] += 0.2
    with pytest.raises(ValueError, match=r"objects\[0\]\.hiding\.probabilities must be one per place, summing to 1"):
        parse_posterior(doc, 2)


@pytest.fixture(scope="module")
def occluded_frame(tmp_path_factory):
    """A generated occluded frame, 320x240: a box in full view, a second object entirely behind it."""
    from workbench.synth import make_scenes

    out = tmp_path_factory.mktemp("occluded")
    make_scenes(out, ["occluded"], 1, seed=1, width=320, height=240, sensor="kinect-like")
    return out


@pytest.mark.slow  # the real renderer and likelihood
def test_a_hidden_object_can_be_at_every_place_of_its_region_and_not_where_the_camera_would_see_it(occluded_frame):
    from workbench.evaluation import LocalEvaluator
    from workbench.inference.answer.hidden import hiding_places
    from workbench.inference.search.geometry import SearchGeometry
    from workbench.inference.search.hiding import line_of_sight
    from workbench.inference.search.scenepoints import project_samples, seen_counts
    from workbench.problem.build import load_bop_problem

    _, problem = load_bop_problem(occluded_frame, 0, 0)
    truth = invert_pose(problem.camera.T_cam_world)[None] @ _.gt_T_cam_obj
    geometry = SearchGeometry.of(problem, upright=False)
    through, on = seen_counts(problem, truth, geometry.samples)
    assert (through + on == 0).tolist() == [False, True]  # the box behind is unseen
    evaluator = LocalEvaluator(problem)
    try:
        score = lambda scenes: evaluator.evaluate(scenes, project=False).loglik  # noqa: E731
        loglik = float(score(truth[None])[0])
        places, gaps, scored = hiding_places(truth, 1, loglik, score, geometry.solids, 45.0)
        in_front = truth.copy()  # 10 cm towards the camera from the box in front: in full view
        in_front[1, :2, 3] = truth[0, :2, 3] - 0.1 * line_of_sight(problem, truth[0, :3, 3])
        seen_loglik = float(score(in_front[None])[0])
    finally:
        evaluator.close()
    assert 0 < scored < len(level_offsets()) and len(places) >= 5  # the places inside the box are not scored
    assert np.array_equal(places[0], truth[1, :3, 3]) and np.all(gaps > -45.0)
    for p in places:  # at each place the sensor sees next to none of it (a place at the region's rim, a few samples)
        moved = truth.copy()
        moved[1, :3, 3] = p
        through, on = seen_counts(problem, moved, geometry.samples)
        assert through[1] + on[1] <= 0.02 * len(project_samples(problem, moved, geometry.samples)[1][0])
    assert seen_loglik < loglik - 45.0
    assert np.linalg.norm(places[:, :2] - in_front[1, :2, 3], axis=1).min() > SPACING


@pytest.mark.slow  # the estimator's settling and posterior sweep, the real renderer and physics
def test_the_estimators_posterior_gives_a_hidden_object_its_region(occluded_frame):
    from workbench.evaluation import LocalEvaluator
    from workbench.inference.config import EstimatorConfig
    from workbench.inference.estimator import Estimator
    from workbench.inference.smc.filter import Update
    from workbench.problem.build import load_bop_problem

    frame, problem = load_bop_problem(occluded_frame, 0, 0)
    truth = invert_pose(problem.camera.T_cam_world)[None] @ frame.gt_T_cam_obj
    evaluator = LocalEvaluator(problem)
    try:
        rested = evaluator.evaluate(truth[None])
        estimator = Estimator(problem, EstimatorConfig(particles=4, seed=0), evaluator)
        estimator.step()
        estimator.filter.apply(Update(estimate=(rested.projected[0].copy(), float(rested.loglik[0]))))
        estimator.settle()
    finally:
        evaluator.close()
    box, behind = estimator.posterior.objects
    assert box.hiding is None and box.confidence > 0.9
    assert isinstance(behind.hiding, HidingRegion) and len(behind.hiding.places) >= 5
    assert np.isclose(sum(m.probability for m in behind.modes), 1.0)  # given its place, as every object's: found
    assert np.isclose(behind.elsewhere, 1.0 - behind.hiding.estimate_share) and behind.elsewhere > 0.5
    assert "hidden: one of" in estimator.posterior.summary(problem)
