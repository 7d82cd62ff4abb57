"""PI-PF and PI-MCPF end to end on a generated frame, with real pybullet and the real renderer."""

import numpy as np
import pytest

from workbench.errors import InputError
from workbench.evaluation import LocalEvaluator, PoolEvaluator, joined, split_calls
from workbench.geometry import invert_pose
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator
from workbench.inference.search.default_search import fit_sink
from workbench.problem.build import load_bop_problem
from workbench.problem.problem import ProblemConfig
from workbench.render.likelihood import LikelihoodConfig
from workbench.score.metrics import position_error, rotation_error

pytestmark = pytest.mark.slow  # needs pybullet and OpenGL


@pytest.fixture(scope="module")
def frame_and_problem(touching_dataset):
    return load_bop_problem(touching_dataset, 0, 0)


def _ground_truth_in_table_frame(frame, problem):
    return invert_pose(problem.camera.T_cam_world)[None] @ frame.gt_T_cam_obj


@pytest.mark.parametrize("method", ["pipf", "mcpf"])
def test_recovers_two_touching_boxes(frame_and_problem, method):
    frame, problem = frame_and_problem
    evaluator = PoolEvaluator(problem, workers=2)
    try:
        estimator = Estimator(problem, EstimatorConfig(method=method, particles=256, iterations=30, seed=1), evaluator)
        best = estimator.run()
    finally:
        evaluator.close()
    gt = _ground_truth_in_table_frame(frame, problem)
    for k, model in enumerate(problem.models):
        assert position_error(gt[k], best[k]) < 0.02, f"object {model.obj_id}"
        assert rotation_error(gt[k], best[k], model.symmetries) < 10.0, f"object {model.obj_id}"
    assert estimator.history[-1].iteration == estimator.iteration
    assert estimator.history[-1].best_loglik > estimator.history[0].best_loglik


def _run(problem, evaluator, steps, **config):
    estimator = Estimator(problem, EstimatorConfig(particles=24, seed=7, **config), evaluator)
    for _ in range(steps):
        estimator.step()
    return estimator


@pytest.mark.parametrize("method", ["pipf", "mcpf"])
def test_seeded_runs_are_reproducible(frame_and_problem, method):
    _, problem = frame_and_problem
    pool = PoolEvaluator(problem, workers=2)
    try:
        a = _run(problem, pool, 3, method=method)
        b = _run(problem, pool, 3, method=method)  # the same workers, which have simulated and drawn a's particles
    finally:
        pool.close()
    assert np.array_equal(a.particles.projected, b.particles.projected)
    assert np.array_equal(a.particles.loglik, b.particles.loglik)


def test_physics_results_do_not_depend_on_the_worker(frame_and_problem):
    """Projection is bit-exact whichever worker runs it; the rendered depth may differ in the last float bits
    with a particle's tile in the framebuffer, so the likelihoods agree to rounding."""
    _, problem = frame_and_problem
    local = LocalEvaluator(problem)
    pool = PoolEvaluator(problem, workers=2)
    try:
        a = _run(problem, local, 1)
        b = _run(problem, pool, 1)
    finally:
        local.close()
        pool.close()
    assert np.array_equal(a.particles.projected, b.particles.projected)
    assert np.allclose(a.particles.loglik, b.particles.loglik, rtol=1e-5)


def test_submitted_batches_equal_their_evaluation_whichever_is_collected_first(frame_and_problem):
    """The estimator hands the workers one batch and prepares the next meanwhile. Batches submitted before any is
    collected (the later one collected first) come back as ``evaluate`` gives them; a large one is held back until
    the one before is received, so no pipe fills both ways."""
    frame, problem = frame_and_problem
    rng = np.random.default_rng(0)
    truth = _ground_truth_in_table_frame(frame, problem)
    batches = []
    for n in (40, 1500):
        h = np.repeat(truth[None], n, axis=0)
        h[:, :, :3, 3] += rng.uniform(-0.02, 0.02, size=h[:, :, :3, 3].shape)
        h[:, :, 2, 3] += 0.005
        batches.append(h)
    pool = PoolEvaluator(problem, workers=2)
    try:
        pending = [pool.submit(h) for h in batches]
        late, early = pending[1].result(), pending[0].result()
        again = [pool.evaluate(h) for h in batches]
    finally:
        pool.close()
    for got, want in zip((early, late), again):
        assert np.array_equal(got.projected, want.projected) and np.array_equal(got.loglik, want.loglik)
    assert len(late.loglik) == 1500 and np.isfinite(late.loglik).mean() > 0.9


@pytest.mark.parametrize("n, parts", [(0, 2), (1, 2), (7, 3), (24, 2), (5, 8)])
def test_calls_are_dealt_out_in_turn_and_their_results_come_back_in_call_order(n, parts):
    """``split_calls`` deals call i to worker i mod parts (neighbouring calls, which cost alike, go to different
    workers), never an empty chunk; ``joined`` puts the chunks' results back in call order."""
    calls = [(i,) for i in range(n)]
    chunks = split_calls(calls, parts)
    assert len(chunks) == min(n, parts) and all(chunks)
    assert all(c[0] % len(chunks) == w for w, chunk in enumerate(chunks) for c in chunk)
    assert joined([[c[0] * 10 for c in chunk] for chunk in chunks]) == [i * 10 for i in range(n)]


def test_map_runs_calls_on_the_workers_in_order_behind_a_pending_batch(frame_and_problem):
    """``Evaluator.map`` (the search's candidate fits) gives what the calls give in this process, in order, also when
    queued behind a batch that has not been collected yet; that batch still comes back as ``evaluate`` gives it."""
    from workbench.inference.search.datadriven import fit_scores
    from workbench.inference.search.scenepoints import model_samples

    frame, problem = frame_and_problem
    truth = _ground_truth_in_table_frame(frame, problem)
    rng = np.random.default_rng(1)
    samples = model_samples(problem.models[0].mesh)
    calls = []
    for n in (1, 7, 3, 12, 5):
        T = np.repeat(truth[:1], n, axis=0)
        T[:, :2, 3] += rng.uniform(-0.03, 0.03, size=(n, 2))
        calls.append((T, samples))
    local = LocalEvaluator(problem)
    pool = PoolEvaluator(problem, workers=2)
    try:
        want = local.map(fit_scores, calls)
        pending = pool.submit(np.repeat(truth[None], 30, axis=0))
        got = pool.map(fit_scores, calls)
        batch = pending.result()
        assert pool.map(fit_scores, []) == []
        alone = local.evaluate(np.repeat(truth[None], 30, axis=0))
    finally:
        local.close()
        pool.close()
    assert len(got) == len(calls) and all(np.array_equal(a, b) for a, b in zip(got, want))
    assert [len(a) for a in got] == [1, 7, 3, 12, 5] and max(a.max() for a in got) > 0
    assert np.array_equal(batch.projected, alone.projected)


def test_a_scene_with_an_object_resting_outside_the_object_region_is_ruled_out(frame_and_problem):
    """The table may go on out of view, but no object is seen beyond the object region: a scene that parks an
    object there gets no likelihood, whatever it would explain."""
    from workbench.physics import STATUS_OUTSIDE, STATUS_REST

    frame, problem = frame_and_problem
    truth = _ground_truth_in_table_frame(frame, problem)
    away = truth.copy()
    away[0, 0, 3] = problem.table.region_max[0] + problem.config.region_margin + 0.05
    assert away[0, 0, 3] < problem.table.x_max  # still on the table: physics alone would keep it
    evaluator = LocalEvaluator(problem)
    try:
        ev = evaluator.evaluate(np.stack([truth, away]))
    finally:
        evaluator.close()
    assert ev.status.tolist() == [STATUS_REST, STATUS_OUTSIDE]
    assert np.isfinite(ev.loglik[0]) and ev.loglik[1] == -np.inf


def test_an_object_hidden_behind_the_region_may_rest_beyond_it(frame_and_problem):
    """The object region bounds what is seen, so an object hidden behind the objects seen may rest beyond it: a
    scene whose second box has its centre on the camera's ray through the first box's centre, beyond the region, is
    admissible; the same box as far beyond the region but beside the first, in plain view of the table, is not."""
    from workbench.evaluation import admissible, hidden_behind_region, in_region
    from workbench.physics import STATUS_AS_GIVEN, STATUS_OUTSIDE

    frame, problem = frame_and_problem
    truth = _ground_truth_in_table_frame(frame, problem)
    centre = truth[0, :3, :3] @ problem.models[0].mesh.bounds.mean(axis=0) + truth[0, :3, 3]
    eye = invert_pose(problem.camera.T_cam_world)[:3, 3]
    ray = (centre - eye) / np.linalg.norm(centre - eye)
    lo = np.asarray(problem.table.region_min) - problem.config.region_margin
    hi = np.asarray(problem.table.region_max) + problem.config.region_margin

    def beyond(p):  # how far (m) the point's xy lies outside the region and its margin
        return float(np.max(np.maximum(lo - p[:2], p[:2] - hi)))

    s = 0.0
    while beyond(centre + s * ray) < 0.02 and s < 2.0:
        s += 0.01
    behind = truth.copy()
    offset = problem.models[1].mesh.bounds.mean(axis=0)
    behind[1, :3, 3] = centre + s * ray - truth[1, :3, :3] @ offset
    aside = behind.copy()
    side = np.cross(ray, [0.0, 0.0, 1.0])
    aside[1, :3, 3] += 0.3 * side / np.linalg.norm(side)
    scenes = np.stack([behind, aside])
    assert beyond(behind[1, :3, 3]) > 0 and beyond(aside[1, :3, 3]) > 0
    assert not in_region(scenes, problem.table, problem.config.region_margin)[:, 1].any()
    assert hidden_behind_region(scenes, problem)[:, 1].tolist() == [True, False]
    assert admissible(scenes, problem).tolist() == [True, False]
    evaluator = LocalEvaluator(problem)
    try:
        ev = evaluator.evaluate(scenes, project=False)
    finally:
        evaluator.close()
    assert ev.status.tolist() == [STATUS_AS_GIVEN, STATUS_OUTSIDE]


def _centre_at_u(problem, T_world_obj: np.ndarray, k: int, u: float) -> np.ndarray:
    """``T_world_obj`` (K, 4, 4) with object ``k`` moved along the camera's x axis, at its depth, until its mesh's
    bounding-box centre projects to image column ``u``."""
    cam = problem.camera
    centre = T_world_obj[k, :3, :3] @ problem.models[k].mesh.bounds.mean(axis=0) + T_world_obj[k, :3, 3]
    p = cam.T_cam_world[:3, :3] @ centre + cam.T_cam_world[:3, 3]
    q = p.copy()
    q[0] = (u - cam.K[0, 2]) * p[2] / cam.K[0, 0]
    moved = T_world_obj.copy()
    moved[k, :3, 3] += cam.T_cam_world[:3, :3].T @ (q - p)
    return moved


def test_a_scene_with_an_object_centred_out_of_view_is_ruled_out(frame_and_problem):
    """An object listed for a frame shows itself there: a scene whose object has its centre beyond the image's
    border is ruled out, however well its visible part would explain clutter cut by that border; one just inside
    is not."""
    from workbench.evaluation import in_view
    from workbench.physics import STATUS_AS_GIVEN, STATUS_OUTSIDE

    frame, problem = frame_and_problem
    truth = _ground_truth_in_table_frame(frame, problem)
    width = problem.camera.width
    inside, beyond = _centre_at_u(problem, truth, 0, width - 2.0), _centre_at_u(problem, truth, 0, width + 2.0)
    behind = truth.copy()
    behind[0, :3, 3] = invert_pose(problem.camera.T_cam_world)[:3, 3] - 0.2 * invert_pose(
        problem.camera.T_cam_world)[:3, 2]  # 20 cm behind the camera, on its axis
    scenes = np.stack([truth, inside, beyond, behind])
    assert in_view(scenes, problem).tolist() == [True, True, False, False]
    evaluator = LocalEvaluator(problem)
    try:
        ev = evaluator.evaluate(np.stack([truth, beyond]), project=False)
    finally:
        evaluator.close()
    assert ev.status.tolist() == [STATUS_AS_GIVEN, STATUS_OUTSIDE]
    assert np.isfinite(ev.loglik[0]) and ev.loglik[1] == -np.inf


def test_particle_count_and_sigma_change_between_steps(frame_and_problem):
    _, problem = frame_and_problem
    evaluator = LocalEvaluator(problem)
    try:
        estimator = _run(problem, evaluator, 2)
        estimator.set_config(EstimatorConfig(particles=40, seed=7, method="mcpf"))
        report = estimator.step()
    finally:
        evaluator.close()
    assert estimator.particles.projected.shape[0] == 40 and estimator.particles.loglik.shape == (40,)
    assert report.iteration == 2 and 0.0 <= report.accept_rate <= 1.0


def test_reduced_state_keeps_roll_and_pitch(frame_and_problem):
    """In the paper's (x, y, z, yaw) state, diffusion never tilts an object: only physics may."""
    from workbench.inference.search.moves.gaussian import propose_joint
    from workbench.inference.smc.particles import Sigma

    rng = np.random.default_rng(0)
    upright = np.tile(np.eye(4), (50, 2, 1, 1))
    moved = propose_joint(rng, upright, Sigma(), np.ones(2), "xyzyaw").hypotheses
    assert np.allclose(moved[..., 2, :3], [0, 0, 1])  # the object's z axis stays vertical
    assert not np.allclose(moved[..., :2, :2], upright[..., :2, :2])  # but it turned


def test_ground_truth_poses_never_reach_the_estimator(touching_dataset, tmp_path):
    """Scrambling scene_gt.json's poses (keeping which objects are present) changes nothing the estimator sees."""
    import json
    import shutil

    scrambled = tmp_path / "scrambled"
    shutil.copytree(touching_dataset, scrambled)
    gt_path = scrambled / "test" / "000000" / "scene_gt.json"
    gt = json.loads(gt_path.read_text())
    for obj in gt["0"]:
        obj["cam_t_m2c"] = [t + 123.0 for t in obj["cam_t_m2c"]]
        obj["cam_R_m2c"] = [1, 0, 0, 0, 1, 0, 0, 0, 1]
    gt_path.write_text(json.dumps(gt))
    runs = []
    for dataset in (touching_dataset, scrambled):
        _, problem = load_bop_problem(dataset, 0, 0)
        evaluator = LocalEvaluator(problem)
        try:
            runs.append(_run(problem, evaluator, 2))
        finally:
            evaluator.close()
    assert np.array_equal(runs[0].particles.projected, runs[1].particles.projected)
    assert np.array_equal(runs[0].particles.loglik, runs[1].particles.loglik)


def test_a_scene_seen_sunk_into_the_table_is_fitted_with_that_sink(frame_and_problem, seeing):
    """Real frames show objects several millimetres below the plane fitted to the table's depth. Here the
    observation is drawn with the true objects 8 mm into the table (the table pixels unchanged): the fitted sink
    must come out near 8 mm, and it must raise the estimate's log-likelihood."""
    frame, problem = frame_and_problem
    gt = _ground_truth_in_table_frame(frame, problem)
    sunk = gt.copy()
    sunk[:, 2, 3] -= 0.008
    sunk_problem = seeing(problem, sunk)
    evaluator = LocalEvaluator(sunk_problem)
    try:
        estimator = Estimator(sunk_problem, EstimatorConfig(particles=4, seed=0), evaluator)
        resting = evaluator.evaluate(gt[None])
        estimator.filter.estimate, estimator.filter.estimate_loglik = resting.projected[0], float(resting.loglik[0])
        estimator.filter.apply(fit_sink(estimator.filter))
        assert 0.006 <= estimator.sink <= 0.010
        assert estimator.estimate_loglik > float(resting.loglik[0])
        for k in range(problem.n_objects):  # the estimate rests at the sink, where the objects were drawn
            assert abs(estimator.estimate[k, 2, 3] - sunk[k, 2, 3]) < 0.003
    finally:
        evaluator.close()


def test_the_clutter_floor_is_weighed_in_after_its_share_of_the_iterations(touching_dataset, frame_and_problem):
    """With the floor on, the first steps weigh hypotheses by the plain mixture (``floor_from``); from ``floor_at``
    on the particles and the estimate carry the whole log-likelihood, scored again as they rest."""
    _, plain = load_bop_problem(touching_dataset, 0, 0,
                                config=ProblemConfig(likelihood=LikelihoodConfig(clutter_floor=None)))
    assert Estimator(plain, EstimatorConfig(), None).filter.floor_in  # no floor: nothing waits
    _, problem = load_bop_problem(touching_dataset, 0, 0,
                                  config=ProblemConfig(likelihood=LikelihoodConfig(clutter_floor=2.0)))
    evaluator = LocalEvaluator(problem)

    def as_resting(estimator):  # the particles, and the estimate sunk 20 cm into the table: its readings unclaimed
        ok = np.isfinite(estimator.particles.loglik)
        sunk = estimator.estimate.copy()
        sunk[:, 2, 3] -= 0.2
        scenes = np.concatenate([estimator.particles.projected[ok], sunk[None]])
        return ok, estimator.filter.evaluate(scenes, project=False).loglik, evaluator.evaluate(scenes, project=False)
    try:
        estimator = Estimator(problem, EstimatorConfig(particles=12, iterations=4, seed=3, floor_from=0.5), evaluator)
        assert estimator.filter.floor_at == 2
        for _ in range(2):  # the start and one iteration
            estimator.step()
        assert not estimator.filter.floor_in and not estimator.converged
        ok, weighed, whole = as_resting(estimator)
        assert ok.sum() >= 6 and whole.floor_gain[-1] > 100.0  # the floor counts where the readings are unclaimed
        np.testing.assert_allclose(weighed, whole.loglik - whole.floor_gain, rtol=1e-9)
        np.testing.assert_allclose(estimator.particles.loglik[ok], weighed[:-1], rtol=1e-5)  # drawn in other tiles
        estimator.step()
        assert estimator.filter.floor_in
        ok, weighed, whole = as_resting(estimator)
        np.testing.assert_allclose(weighed, whole.loglik, rtol=1e-9)
        np.testing.assert_allclose(estimator.particles.loglik[ok], weighed[:-1], rtol=1e-5)
        best = evaluator.evaluate(estimator.estimate[None], project=False).loglik[0]
        assert estimator.estimate_loglik == pytest.approx(best, rel=1e-5) and best >= whole.loglik[:-1].max() - 1.0
    finally:
        evaluator.close()


def test_the_clutter_floor_comes_in_once_the_estimate_is_calm(touching_dataset):
    """``floor_calm``: once the estimate has been calm for that many iterations, the floor comes in at the next step,
    long before ``floor_from``; with None it waits for ``floor_from``."""
    with pytest.raises(InputError, match="floor_calm"):
        EstimatorConfig(floor_calm=0).validate()
    _, problem = load_bop_problem(touching_dataset, 0, 0,
                                  config=ProblemConfig(likelihood=LikelihoodConfig(clutter_floor=2.0)))
    evaluator = LocalEvaluator(problem)
    try:
        for floor_calm in (1, None):
            estimator = Estimator(problem, EstimatorConfig(particles=12, iterations=8, seed=3, floor_from=1.0,
                                                           floor_calm=floor_calm), evaluator)
            estimator.step()
            while estimator.filter.calm < 1 and estimator.filter.iteration < 6:
                estimator.step()
            assert estimator.filter.calm == 1 and not estimator.filter.floor_in
            estimator.step()
            assert estimator.filter.floor_in == (floor_calm is not None)
            assert estimator.filter.iteration + 1 < estimator.filter.floor_at
    finally:
        evaluator.close()


def test_an_assembly_that_nearly_beats_the_estimate_is_fitted_to_the_depth(frame_and_problem):
    """Both objects a centimetre off, as candidates fitted alone come out: the assembly is fitted to the depth,
    once; one that loses to the estimate by more than FIT_WITHIN is another arrangement and is not fitted. A move of
    one object to another place is fitted only from a pool that asks for one (polish's moves), not among the
    assemblies (two or more)."""
    from workbench.inference.search import default_search

    frame, problem = frame_and_problem
    gt = _ground_truth_in_table_frame(frame, problem)
    off = gt.copy()
    off[:, 0, 3] += 0.01
    off[:, 1, 3] -= 0.006
    evaluator = LocalEvaluator(problem)
    try:
        estimator = _run(problem, evaluator, 1)
        filt, search = estimator.filter, estimator.search
        estimate = off.copy()
        estimate[:, 0, 3] += 0.1  # both objects elsewhere, so the assembly moves both
        near_miss = filt.estimate_loglik - default_search.FIT_WITHIN / 2
        far = filt.estimate_loglik - 2 * default_search.FIT_WITHIN

        def fitted(scene: np.ndarray, loglik: float, least: int) -> np.ndarray:
            return default_search.fit_near_misses(filt, [(scene[None], np.array([loglik]), least, 2)], estimate,
                                                  search.fitted)[0]

        assert len(fitted(off, far, 2)) == 0
        both, again = fitted(off, near_miss, 2), fitted(off, near_miss, 2)
        one = estimate.copy()
        one[0] = off[0]  # only the first object moved back
        assert len(fitted(one, near_miss, 2)) == 0
        alone = fitted(one, near_miss, 1)
    finally:
        evaluator.close()
    assert both.shape == (1, problem.n_objects, 4, 4) and len(again) == 0
    for k in range(problem.n_objects):
        assert position_error(gt[k], both[0, k]) < 0.004 < position_error(gt[k], off[k])
    assert alone.shape == (1, problem.n_objects, 4, 4)
    assert position_error(gt[0], alone[0, 0]) < 0.004 and np.array_equal(alone[0, 1], estimate[1])


def test_the_assemblies_fitted_and_the_last_polish_are_saved_with_the_search_state(frame_and_problem):
    """A restored run must not fit an assembly again, nor judge the next polish stuck otherwise, nor offer again
    what the last polish offered for the same estimate: all travel in the state's JSON search entry; a fitted
    assembly naming an object the problem lacks, or an offered scene that is no digest, is refused."""
    import json

    from workbench.inference.estimator import parse_search

    _, problem = frame_and_problem
    evaluator = LocalEvaluator(problem)
    try:
        estimator = _run(problem, evaluator, 1)
        search = estimator.search
        pose = tuple(np.round(np.eye(4) + 1e-7 / 3, 6).ravel().tolist())
        search.fitted = {((0, pose), (1, pose))}
        search.polished_at = 1234.5678
        search.offered_for, search.offered = "an estimate", {"0123456789abcdef", "fedcba9876543210"}
        state = estimator.state_dict()
        state["search"] = json.loads(json.dumps(state["search"]))
        restored = Estimator(problem, EstimatorConfig(particles=24, seed=7), evaluator)
        restored.load_state(state)
    finally:
        evaluator.close()
    assert restored.search.fitted == search.fitted and restored.search.polished_at == 1234.5678
    assert restored.search.offered == search.offered and restored.search.offered_for == "an estimate"
    state["search"]["offered"].append(3)
    with pytest.raises(ValueError, match="offered"):
        parse_search(state["search"], problem.n_objects)
    state["search"]["offered"].pop()
    state["search"]["fitted"][0][1][0] = problem.n_objects
    with pytest.raises(ValueError, match="fitted"):
        parse_search(state["search"], problem.n_objects)


def test_a_polish_of_an_unchanged_estimate_evaluates_nothing_it_offered_before(frame_and_problem):
    """Polish offers the same variants of an estimate that has not moved; once offered, they lose to it again, so
    they are not evaluated again: a third polish of the same estimate (the second was stuck, with its wider beam and
    leaning starts) projects nothing. Once the estimate changes, polish offers its variants again."""
    _, problem = frame_and_problem
    evaluator = LocalEvaluator(problem)
    try:
        estimator = _run(problem, evaluator, 1)
        filt, search = estimator.filter, estimator.search
        search.polish(filt)
        search.polish(filt)  # stuck: leaning starts, a wider beam
        before = filt.evaluations
        assert search.polish(filt).offered is None and filt.evaluations == before
        filt.estimate = filt.estimate.copy()
        filt.estimate[0, 0, 3] += 0.001
        search.polish(filt)
        assert filt.evaluations > before
    finally:
        evaluator.close()


def test_the_paper_search_keeps_the_objects_on_the_fitted_plane(frame_and_problem):
    _, problem = frame_and_problem
    evaluator = LocalEvaluator(problem)
    try:
        estimator = _run(problem, evaluator, 3, proposals="paper")
    finally:
        evaluator.close()
    assert estimator.sink == 0.0


def test_polish_puts_back_two_objects_that_took_each_others_places(frame_and_problem):
    frame, problem = frame_and_problem
    gt = _ground_truth_in_table_frame(frame, problem)
    swapped = gt.copy()
    swapped[0, :2, 3], swapped[1, :2, 3] = gt[1, :2, 3], gt[0, :2, 3]
    evaluator = LocalEvaluator(problem)
    try:
        estimator = _run(problem, evaluator, 1)
        wrong = evaluator.evaluate(swapped[None])
        estimator.filter.estimate, estimator.filter.estimate_loglik = wrong.projected[0], float(wrong.loglik[0])
        estimator.filter.apply(estimator.search.polish(estimator.filter))
    finally:
        evaluator.close()
    assert estimator.estimate_loglik > float(wrong.loglik[0])
    for k in range(problem.n_objects):
        assert position_error(gt[k], estimator.estimate[k]) < 0.02
    assert estimator.estimate_kind.label == "polish"
    assert np.any(estimator.particles.kinds == 10) and np.all(np.isfinite(estimator.particles.loglik))
