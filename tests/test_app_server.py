"""The workbench server without a browser: the viser-edge conversions, and surviving crashed processes."""

from __future__ import annotations

import io
import os
import signal

import numpy as np
import pytest
from headless import free_port, image_stats
from inbox import Inbox

from workbench.app import protocol as p
from workbench.app.ui.run.views import wxyz_from_matrices
from workbench.app.ui.widgets.colors import MISSING, VIRIDIS, apply_map
from workbench.geometry import matrix_to_quat_wxyz, quat_wxyz_to_matrix, random_rotations, rot_x, rot_z

pytestmark = pytest.mark.slow  # needs the engine process: pybullet and OpenGL


def test_wxyz_from_matrices_matches_geometry_including_half_turns():
    rng = np.random.default_rng(0)
    R = np.concatenate([random_rotations(rng, 200), rot_x(np.array([np.pi, np.pi - 1e-7])), rot_z(np.array([np.pi]))])
    q = wxyz_from_matrices(R)
    assert np.allclose(quat_wxyz_to_matrix(q), R, atol=1e-6)
    ref = matrix_to_quat_wxyz(R)
    assert np.allclose(np.abs(np.sum(q * ref, axis=-1)), 1.0, atol=1e-6)  # same rotation (q and -q alike)


def test_apply_map_ends_and_missing():
    rgb = apply_map(np.array([-1.0, 0.0, 1.0, 2.0, np.nan]), 0.0, 1.0)
    assert (rgb[0] == VIRIDIS[0]).all() and (rgb[1] == VIRIDIS[0]).all()
    assert (rgb[2] == VIRIDIS[-1]).all() and (rgb[3] == VIRIDIS[-1]).all()
    assert (rgb[4] == MISSING).all()


def test_image_stats_tell_blank_from_drawn():
    from PIL import Image

    def png(a):
        buf = io.BytesIO()
        Image.fromarray(a).save(buf, format="PNG")
        return buf.getvalue()

    blank = np.full((60, 80, 3), 255, np.uint8)
    drawn = blank.copy()
    drawn[20:40, 20:60] = (30, 90, 200)
    assert image_stats(png(blank)) == (0.0, 0.0)
    std, frac = image_stats(png(drawn))
    assert std > 10 and 0.15 < frac < 0.2


def test_dead_worker_and_dead_engine_are_restarted_and_the_run_goes_on(capfd, caplog):
    import logging

    from workbench.app.ui.server import serve
    from workbench.inference.config import EstimatorConfig

    caplog.set_level(logging.WARNING)

    handle = serve(demo=True, block=False, port=free_port(), workers=2,
                   config=EstimatorConfig(particles=16, iterations=50))
    app = handle.app
    try:
        assert app.wait_for(lambda s: s.view is not None and len(s.worker_pids) == 2, 180), app.state.failures
        app.send(p.Step())
        assert app.wait_for(lambda s: s.iteration == 0, 120)

        # A worker dies between iterations: the next step finds out, a new pool takes over, the step is retried.
        dead = app.state.worker_pids[0]
        os.kill(dead, signal.SIGKILL)
        app.send(p.Step())
        assert app.wait_for(lambda s: s.iteration == 1, 120), app.state.failures
        assert app.state.restarts == 1 and dead not in app.state.worker_pids
        assert not app.state.failures

        # The estimator process itself dies: the server starts a new one and reloads the frame.
        old = app.state.engine_pid
        os.kill(old, signal.SIGKILL)
        assert app.wait_for(lambda s: s.engine_pid not in (None, old) and s.view is not None
                            and s.last_state is not None and s.last_state.reason == "reset", 180)
        assert app.state.restarts == 2
        app.send(p.Step())
        assert app.wait_for(lambda s: s.iteration == 0, 120), app.state.failures
        assert not app.state.display_errors
    finally:
        handle.stop()
    # Both crashes are in the server's log at WARNING: the worker's in the engine process's stderr, the engine's
    # in the server's own log.
    assert "an evaluation worker died" in capfd.readouterr().err
    assert any(r.levelno == logging.WARNING and "estimator process died" in r.getMessage() for r in caplog.records)


def test_engine_session_continues_bit_for_bit_with_its_labels(tmp_path):
    """Save a session from the engine mid-run (settings changed on the way, one object labelled), step on; a fresh
    engine (a restarted server) loads it and its next steps equal the original's bit for bit. A damaged session
    file is an error message; the run that was loaded goes on."""
    from dataclasses import replace

    from workbench.app.engine.engine import Engine
    from workbench.inference.config import EstimatorConfig
    from workbench.inference.smc.particles import Sigma

    config = EstimatorConfig(particles=12, iterations=50, sigma=Sigma(x=0.007, y=0.013, z=0.003, yaw=0.1234), seed=5)
    first, second = Inbox(), Inbox()
    engine = Engine(first, workers=1)
    restored = None
    try:
        engine.handle(p.Load(p.Source(demo=True), config, "robust"))
        engine.step()
        engine.handle(p.SetConfig(replace(config, particles=16, data_start=0.5)))
        engine.step()
        label = engine.estimator.estimate[1].copy()
        engine.handle(p.SetLabels((None, label), heatmap=True))
        engine.labels.work()
        assert first.of(p.LabelHeatmap)[-1].filled == "best estimate"
        assert first.of(p.LabelErrors)[-1].errors[1]["position_error_m"] == 0.0
        engine.handle(p.SaveSession(tmp_path, "run"))
        assert first.of(p.Saved)[-1].kind == "session", first.of(p.Failure)
        engine.step(), engine.step()
        expected = engine.estimator.particles.copy().arrays()

        (tmp_path / "damaged.json").write_text("{")
        engine.handle(p.LoadSession(tmp_path / "damaged.json"))
        failure = first.of(p.Failure)[-1]
        assert failure.topic == "session" and failure.path.endswith("damaged.json") and "not JSON" in failure.problem
        engine.step()  # the loaded run is untouched
        assert engine.estimator.iteration == 4

        restored = Engine(second, workers=1)
        restored.handle(p.LoadSession(tmp_path / "run.json"))
        assert not second.of(p.Failure) and not second.of(p.SessionQuestion)
        msg = second.of(p.SessionRestored)[-1]
        assert msg.config == replace(config, particles=16, data_start=0.5) and len(msg.reports) == 2
        assert np.array_equal(second.of(p.Labels)[-1].labels[1], label) and second.of(p.Labels)[-1].labels[0] is None
        restored.step(), restored.step()
        for name, value in expected.items():
            assert np.array_equal(getattr(restored.estimator.particles, name), value), name
    finally:
        engine.close()
        if restored is not None:
            restored.close()


def test_panel_shows_a_restored_config_without_changing_it():
    """Sigma travels through the panel in cm and degrees, which do not round-trip to the last bit (these values
    do not): a restored session's settings, shown and read back, must stay exactly what was saved."""
    import viser

    from workbench.app.ui.run.estimator_tab import build_estimator_tab
    from workbench.inference.config import EstimatorConfig
    from workbench.inference.smc.particles import Sigma

    saved = EstimatorConfig(method="mcpf", particles=77, iterations=9, seed=3,
                            sigma=Sigma(x=0.0474, y=0.0156, z=0.0205, roll=0.0099, pitch=0.1524, yaw=0.0792))
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        panel = build_estimator_tab(server.gui, EstimatorConfig(), "robust")
        panel.show_config(saved, "ssd")
        assert panel.estimator_config(saved) == saved
        assert panel.likelihood.value == "ssd"
        panel.sigma_z.value = 0.5  # an edit still takes effect
        assert panel.estimator_config(saved).sigma.z == 0.005
    finally:
        server.stop()


def test_a_running_engine_starts_an_iteration_only_once_the_server_shows_the_last():
    """Flow control between engine and server: a run never gets ahead of the display by more than the iteration
    in progress, so a Pause pressed while iteration k is shown stops it at k + 1 at the latest."""
    from workbench.app.engine.engine import Engine
    from workbench.inference.config import EstimatorConfig

    engine = Engine(Inbox(), workers=1)
    try:
        engine.handle(p.Load(p.Source(demo=True), EstimatorConfig(particles=12, iterations=50), "robust"))
        engine.handle(p.Run(stop_on_convergence=False))
        assert engine.may_step()
        engine.step()
        assert engine.running and not engine.may_step()  # iteration 0 is on its way to the server
        engine.handle(p.Shown(engine.estimator.iteration - 1))  # an older snapshot shown: still waiting
        assert not engine.may_step()
        engine.handle(p.Shown(engine.estimator.iteration))
        assert engine.may_step()
        engine.step()
        # The server sends a Pause before the Shown of any later iteration: the run stops there.
        engine.handle(p.Pause())
        engine.handle(p.Shown(engine.estimator.iteration))
        assert not engine.running and not engine.may_step() and engine.estimator.iteration == 1
        engine.handle(p.Reset(EstimatorConfig(particles=12, iterations=50), "robust"))
        engine.handle(p.Run())
        assert engine.may_step()  # a fresh run waits for nothing from the old one
    finally:
        engine.close()


def test_a_run_with_a_budget_stops_by_it_answers_and_says_what_it_cut():
    """A Run whose budget (0.01 s: shorter than any iteration, on any machine) is spent stops after one iteration
    with the answer it has, its posterior and the status saying what was cut; a Step after it is a run of its own."""
    from workbench.app.engine.engine import Engine
    from workbench.app.ui.run.status import RunView, status_markdown
    from workbench.inference.config import EstimatorConfig

    engine = Engine(Inbox(), workers=1)
    config = EstimatorConfig(particles=12, iterations=50, budget_s=0.01)
    try:
        engine.handle(p.Load(p.Source(demo=True), config, "robust"))
        engine.handle(p.Run(stop_on_convergence=False))
        engine.step()
        assert not engine.running and engine.estimator.iteration == 0
        assert engine.results.of(p.RunState)[-1].reason == "budget spent"
        snapshot = engine.results.of(p.Snapshot)[-1]
        assert snapshot.report["cut_short"] == "iterations, settle" and snapshot.report["budget_left_s"] == 0.0
        assert snapshot.posterior is not None and snapshot.posterior.cut_short == "iterations, settle"
        status = status_markdown(RunView(iteration=0, reports=[snapshot.report]), config)
        assert "the budget cut short iterations, settle" in status
        # While it ran, the server heard of each stage it entered, in order, with the run's seconds so far.
        stages = engine.results.of(p.Stage)
        assert [m.name for m in stages][:3] == ["filter", "start", "library"]
        assert "settle" not in {m.name for m in stages}
        assert all(a.seconds <= b.seconds for a, b in zip(stages, stages[1:]))
        running = status_markdown(RunView(running=True, stage=p.Stage("library", 3.2)), config)
        assert running.endswith("running: fitting candidates to the points (3 s into the run)")
        # The calm count is the filter's own, and says when the clutter floor still has to come in.
        assert snapshot.report["calm"] == engine.estimator.filter.calm
        assert snapshot.report["floor_in"] is True  # the answer is weighed with the floor in
        moved = {**snapshot.report, "best_move_m": 0.0, "best_move_deg": 0.0, "calm": 3, "converged": False,
                 "floor_in": False, "cut_short": None}
        calm = status_markdown(RunView(running=True, reports=[moved]), config)
        patience = config.converge_patience
        assert f"calm 3/{patience}" in calm and "clutter floor" not in calm
        calm = status_markdown(RunView(running=True, reports=[{**moved, "calm": 12}]), config)
        assert f"calm {patience}/{patience}" in calm and "waiting for the clutter floor" in calm
        # Pause pressed: the run says it stops after the iteration under way, until it has.
        stopping = status_markdown(RunView(running=True, reports=[moved], pause_requested_at=0,
                                           stage=p.Stage("polish", 5.0)), config)
        assert "stopping after this iteration" in stopping and "running" not in stopping
        assert "stopping after the first" in status_markdown(RunView(running=True, pause_requested_at=-1), config)
        assert "stopping" not in status_markdown(RunView(reports=[moved], pause_requested_at=0), config)
        engine.handle(p.Step())  # with the same budget, spent before its polish: its own cut, not the Run's
        assert engine.estimator.iteration == 1 and engine.estimator.cut_short == "polish"
    finally:
        engine.close()


def test_serve_starts_from_a_saved_session_and_a_damaged_one_only_gets_a_message(tmp_path, capsys):
    from workbench.app.engine.engine import Engine
    from workbench.app.ui.server import serve
    from workbench.cli import main
    from workbench.inference.config import EstimatorConfig

    config = EstimatorConfig(particles=12, iterations=50)
    engine = Engine(Inbox(), workers=1)
    try:
        engine.handle(p.Load(p.Source(demo=True), config, "robust"))
        engine.step(), engine.step()
        label = engine.estimator.estimate[0].copy()
        engine.handle(p.SetLabels((label, None)))
        engine.handle(p.SaveSession(tmp_path, "start"))
    finally:
        engine.close()
    (tmp_path / "damaged.json").write_text('{"format_version": 1, "kind": "workbench-session"')

    # The command line refuses a bad session file before starting anything.
    assert main(["serve", "--session", str(tmp_path / "damaged.json")]) == 2
    assert "damaged.json: corrupt session file" in capsys.readouterr().err

    handle = serve(session=tmp_path / "start.json", block=False, port=free_port(), workers=1)
    app = handle.app
    try:
        assert app.wait_for(lambda s: s.view is not None and s.iteration == 1 and s.cloud is not None, 180), \
            app.state.failures
        assert "session start" in app.state.view.title and app.config == config
        assert np.array_equal(app.labelling.editor.labels[0], label) and app.labelling.editor.labels[1] is None
        assert app.sessions.directory == tmp_path.resolve()  # the session's folder is the list's
        assert "**damaged** — ⚠ cannot be loaded" in app.sessions.tab.listing.content

        app.sessions.tab.choice.value = "damaged"
        app.ui.call(app.sessions.load)
        assert app.wait_for(lambda s: any(f.topic == "session" for f in s.failures), 60)
        assert "damaged.json" in app.sessions.tab.message.content and app.reporter.error.visible
        app.send(p.Step())
        assert app.wait_for(lambda s: s.iteration == 2, 60), app.state.failures
        assert "session start" in app.state.view.title and not app.state.display_errors
        # Loading a frame: Step and Run wait, and say why, until the engine has it (or refused it).
        waiting = app.ui.call(lambda: (app.load(p.Source(demo=True)), app.buttons.run.disabled,
                                       app.buttons.step.disabled, app.buttons.busy.content)[1:])
        assert waiting[:2] == (True, True) and "Loading the frame" in waiting[2]
        assert app.wait_for(lambda s: s.iteration == -1 and not app.buttons.run.disabled, 120), app.state.failures
        app.ui.call(app.load, p.Source(dataset=tmp_path / "nowhere", scene_id=0, im_id=0))
        assert app.wait_for(lambda s: not app.buttons.run.disabled and any(
            "nowhere" in f"{f.path} {f.problem}" for f in s.failures), 60), app.state.failures
    finally:
        handle.stop()


def test_engine_labels_files_and_a_changed_dataset_asks_before_loading(tmp_path):
    """Labels go to scene_gt_labels.json and come back with the frame; scene_gt.json is written only when asked,
    after a backup. A session whose dataset changed is loaded only after a confirmation."""
    import shutil

    from workbench.app.engine.engine import DEMO_DIR, Engine
    from workbench.inference.config import EstimatorConfig

    dataset = tmp_path / "demo"
    shutil.copytree(DEMO_DIR, dataset)
    scene = dataset / "test" / "000000"
    original = (scene / "scene_gt.json").read_bytes()
    inbox = Inbox()
    engine = Engine(inbox, workers=1)
    try:
        source = p.Source(dataset=dataset, scene_id=0, im_id=0)
        engine.handle(p.Load(source, EstimatorConfig(particles=12), "robust"))
        engine.handle(p.SaveLabels())
        assert "nothing is labelled" in inbox.of(p.Failure)[-1].problem
        engine.step()
        engine.handle(p.UseBestAsLabel())
        labels = [T.copy() for T in inbox.of(p.Labels)[-1].labels]
        engine.handle(p.SaveLabels())
        assert inbox.of(p.Saved)[-1].path == str(scene / "scene_gt_labels.json")
        assert (scene / "scene_gt.json").read_bytes() == original
        engine.handle(p.SaveLabels(overwrite_original=True))
        assert inbox.of(p.Saved)[-1].path == str(scene / "scene_gt.json") and "scene_gt.json.bak-" in \
            inbox.of(p.Saved)[-1].note
        assert [b.read_bytes() for b in scene.glob("scene_gt.json.bak-*")] == [original]

        engine.handle(p.Load(source, EstimatorConfig(particles=12), "robust"))  # the labels come back with the frame
        back = inbox.of(p.Labels)[-1]
        assert "read from" in back.note and all(np.allclose(a, b, atol=1e-9) for a, b in zip(back.labels, labels))

        engine.handle(p.SaveSession(tmp_path / "sessions", "s"))
        info = dataset / "models" / "models_info.json"
        info.write_text(info.read_text() + " ")  # same content, other bytes: the checksum no longer matches
        engine.handle(p.LoadSession(tmp_path / "sessions" / "s.json"))
        question = inbox.of(p.SessionQuestion)[-1]
        assert any("models_info.json: changed" in w for w in question.warnings) and not inbox.of(p.SessionRestored)
        engine.handle(p.LoadSession(question.path, confirmed=True))
        assert inbox.of(p.SessionRestored)[-1].warnings == question.warnings
    finally:
        engine.close()


def test_engine_restores_a_backup_and_the_truth_table_follows_scene_gt(tmp_path):
    """An overwriting save and a restore each read the frame's truth again (drawn, scored, the Plots' reference);
    the restore backs up the current scene_gt.json first; no backups and a damaged one are messages naming the
    file, with nothing written."""
    import shutil

    from workbench.app.engine.engine import DEMO_DIR, Engine
    from workbench.inference.config import EstimatorConfig

    dataset = tmp_path / "demo"
    shutil.copytree(DEMO_DIR, dataset)
    scene_gt = dataset / "test" / "000000" / "scene_gt.json"
    original = scene_gt.read_bytes()
    inbox = Inbox()
    engine = Engine(inbox, workers=1)
    try:
        engine.handle(p.Load(p.Source(dataset=dataset, scene_id=0, im_id=0), EstimatorConfig(particles=12), "robust"))
        engine.handle(p.ListBackups())
        assert inbox.of(p.Backups)[-1].backups == [] and inbox.of(p.Backups)[-1].path == str(scene_gt)
        engine.step()
        truth = engine.frame.gt_T_cam_obj.copy()
        engine.handle(p.UseBestAsLabel())
        engine.handle(p.SaveLabels(overwrite_original=True))
        drawn = inbox.of(p.TruthReloaded)[-1].gt_T_world_obj
        label = engine.labels.labels[0]
        assert np.allclose(drawn[0], label, atol=1e-9) and not np.allclose(engine.frame.gt_T_cam_obj, truth)
        assert inbox.of(p.TruthErrors)[-1].rows[0]["position_cm"] < 1e-6  # the estimate against its own label
        assert engine.labels.reference is None  # the Plots' truth log-likelihood is computed again
        (name, _), = inbox.of(p.Backups)[-1].backups

        engine.handle(p.RestoreBackup(name))
        assert scene_gt.read_bytes() == original and np.allclose(engine.frame.gt_T_cam_obj, truth, atol=1e-9)
        restored = inbox.of(p.Saved)[-1]
        assert restored.kind == "ground truth" and name in restored.note
        assert len(inbox.of(p.Backups)[-1].backups) == 2  # the labelled scene_gt.json was kept too

        damaged = scene_gt.with_name("scene_gt.json.bak-20200101T000000000000")
        damaged.write_text('{"0": [')
        engine.handle(p.RestoreBackup(damaged.name))
        failure = inbox.of(p.Failure)[-1]
        assert failure.path == str(damaged) and "corrupt JSON" in failure.problem and failure.topic == "labels"
        assert scene_gt.read_bytes() == original and len(list(scene_gt.parent.glob("scene_gt.json.bak-*"))) == 3
        engine.step()  # the run goes on
    finally:
        engine.close()


def test_object_names_come_from_models_info_with_the_bop_default(tmp_path):
    """models_info.json's ``name`` where present, else obj_000006; a repeated model gets " #2" in the scene."""
    import json
    import shutil

    from workbench.app.engine.engine import demo_dataset
    from workbench.errors import InputError
    from workbench.io import bop
    from workbench.problem.scene import display_names

    src = demo_dataset()
    data = tmp_path / "named"
    shutil.copytree(src / "models", data / "models")
    info_path = data / "models" / "models_info.json"
    info = json.loads(info_path.read_text())
    first, second = sorted(info, key=int)[:2]
    assert info[first]["name"] == "wood_block"  # the demo's models are named
    info[first]["name"] = "  cracker box "
    del info[second]["name"]
    info_path.write_text(json.dumps(info))
    models = bop.load_models(data)
    assert models[int(first)].name == "cracker box"
    assert models[int(second)].name == f"obj_{int(second):06d}"
    assert display_names([models[int(first)], models[int(second)], models[int(first)]]) == \
        ["cracker box", f"obj_{int(second):06d}", "cracker box #2"]
    info[first]["name"] = 7
    info_path.write_text(json.dumps(info))
    try:
        bop.load_models(data)
    except InputError as err:
        assert str(err.path) == str(info_path) and "name" in err.problem
    else:
        raise AssertionError("a non-text name was accepted")


def test_plots_columns_and_acceptance_by_move_kind():
    from workbench.app.ui.run.plots import CHARTS, legend_html

    def report(i, moves=None, accept=float("nan")):
        r = {"iteration": i, "best_loglik": -100.0 + i, "mean_loglik": -150.0 + i, "beta": 0.01 * (i + 1),
             "best_move_m": 0.02 if i else 0.0, "best_move_deg": 1.0, "accept_rate": accept,
             "distinct_after_resampling": 30.0 + i, "truth_loglik": -90.0, "label_loglik": -95.0 if i == 2 else None}
        if moves is not None:
            r["moves"] = moves
        return r

    ctx = {"converge_m": 0.01, "converge_deg": 3.0, "particles": [64, 64, 64]}
    charts = {c.key: c for c in CHARTS}
    plain = [report(i) for i in range(3)]
    assert charts["acceptance"].columns(plain, ctx) is None  # PI-PF, no move kinds: no chart
    pipf = [report(i, {"diffuse": {"proposed": 60, "accepted": 30}}) for i in range(3)]
    assert charts["acceptance"].columns(pipf, ctx) is None  # PI-PF's per-kind counts are not acceptances
    # The truth's and the labels' levels apart, each the latest value across the run.
    x, best, mean, truth, labels = charts["loglik"].columns(plain, ctx)
    assert list(x) == [0, 1, 2] and list(truth) == [-90.0] * 3 and list(labels) == [-95.0] * 3
    assert [ln.label for ln in charts["loglik"].lines(plain)] == ["best", "mean", "truth", "labels"]
    assert [ln.label for ln in charts["loglik"].lines(plain[:2])] == ["best", "mean", "truth"]
    # The clutter floor weighed in from iteration 2: the best before it as a level, named with that iteration.
    floored = [{**r, "floor_in": r["iteration"] >= 2} for r in plain]
    x, best, mean, truth, labels, floor = charts["loglik"].columns(floored, ctx)
    assert list(floor) == [-99.0] * 3
    assert charts["loglik"].lines(floored)[-1].label == "best before the clutter floor (in from iteration 2)"
    # The convergence ratio on a log scale: a move of nothing sits at the floor, not at zero.
    x, position, angle, rule = charts["move"].columns(plain, ctx)
    assert position[0] > 0 and np.isclose(position[1], 2.0) and list(rule) == [1.0] * 3
    assert charts["move"].y_scale.get("distr") == 3
    x, distinct, n = charts["distinct"].columns(plain, ctx)
    assert list(distinct) == [30.0, 31.0, 32.0] and list(n) == [64.0] * 3
    moves = [report(i, {"diffuse": {"proposed": 60, "accepted": 30}, "turn": {"proposed": 4, "accepted": i}},
                    accept=0.5) for i in range(3)]
    assert [ln.label for ln in charts["acceptance"].lines(moves)] == ["all", "diffuse", "turn"]
    x, overall, diffuse, turn = charts["acceptance"].columns(moves, ctx)
    assert list(diffuse) == [0.5] * 3 and list(turn) == [0.0, 0.25, 0.5]
    assert "turn" in legend_html(charts["acceptance"], charts["acceptance"].lines(moves))


def test_particles_drawn_by_default_share_one_budget_of_outlines():
    """A frame of more objects draws fewer particles each until the user sets the count: software WebGL pays per
    outline. The demo's two objects keep 32."""
    from workbench.app.engine.snapshot import DEFAULT_DISPLAY, MIN_DISPLAY, OUTLINE_BUDGET, default_drawn

    assert default_drawn(1) == default_drawn(2) == DEFAULT_DISPLAY == 32
    assert default_drawn(4) == 16 and 4 * default_drawn(4) == OUTLINE_BUDGET
    assert default_drawn(6) == 10
    assert default_drawn(50) == MIN_DISPLAY


def test_expected_distinct_particles_matches_systematic_resampling():
    from workbench.app.engine.snapshot import expected_distinct
    from workbench.inference.smc.resampling import systematic_resample

    rng = np.random.default_rng(3)
    logw = rng.normal(0.0, 2.0, 200)
    w = np.exp(logw - logw.max())
    w /= w.sum()
    counts = [len(np.unique(systematic_resample(logw, rng, 200))) for _ in range(400)]
    assert abs(np.mean(counts) - expected_distinct(w, 200)) < 0.5
    assert expected_distinct(np.full(10, 0.1), 10) == 10.0  # even weights: every particle kept


def test_turns_and_laying_on_a_face_keep_the_object_on_the_table():
    import trimesh

    from workbench.app.ui.labelling.controls import FACES
    from workbench.app.ui.labelling.editor import laid_on, turned
    from workbench.geometry import make_pose

    box = np.asarray(trimesh.creation.box(extents=(0.1, 0.06, 0.02)).vertices)
    T = make_pose(np.eye(3), [0.05, -0.02, 0.01])  # resting on its largest face
    up = turned(T, rot_x(np.pi / 2), box)
    assert np.isclose(np.min((box @ up[:3, :3].T)[:, 2]) + up[2, 3], 0.0)  # still on the table
    assert np.isclose(up[2, 3], 0.03) and np.allclose(up[:2, 3], T[:2, 3])
    for name, face in FACES.items():
        L = laid_on(up, face, box)
        assert np.allclose(L[:3, :3] @ np.array(face, float), [0, 0, -1], atol=1e-9), name
        assert np.isclose(np.min((box @ L[:3, :3].T)[:, 2]) + L[2, 3], 0.0), name
        assert np.allclose(L[:2, 3], T[:2, 3])


def test_outlines_are_feature_edges_not_every_triangle():
    import trimesh

    from workbench.app.engine.observation import outline_edges
    from workbench.app.protocol import MeshData
    from workbench.app.ui.run.views import outline_mesh, outline_segments

    box = trimesh.creation.box(extents=(0.1, 0.06, 0.02))
    edges = outline_edges(box.vertices, box.faces)
    assert edges.shape == (12, 2, 3)  # a box's 12 edges, not its 18 triangle edges
    can = trimesh.creation.cylinder(radius=0.05, height=0.1, sections=64)
    assert len(outline_edges(can.vertices, can.faces)) < len(can.edges_unique)
    mesh = MeshData("box", box.vertices.astype(np.float32), box.faces.astype(np.int32), edges)
    vertices, faces = outline_mesh(mesh)
    assert faces.shape == (12, 3) and np.all(faces[:, 1] == faces[:, 2])  # degenerate: the wireframe is the line
    assert len(outline_segments(MeshData("box", mesh.vertices, mesh.faces))) == 18  # no outline: every edge


def test_particles_get_a_coarser_outline_and_a_scan_with_too_many_edges_its_box(monkeypatch):
    import trimesh

    from workbench.app.engine import observation
    from workbench.app.engine.observation import CLOUD_MAX_EDGES, cloud_outline, outline_edges
    from workbench.app.protocol import MeshData
    from workbench.app.ui.run.views import outline_mesh

    rock = trimesh.creation.icosphere(4, radius=0.05)  # a bumpy scan: many feature edges
    rock.vertices *= 1 + 0.08 * np.random.default_rng(0).random((len(rock.vertices), 1))
    fine, coarse = outline_edges(rock.vertices, rock.faces), cloud_outline(rock)
    assert len(coarse) <= CLOUD_MAX_EDGES and 3 * len(coarse) < len(fine)
    # Still too many edges (YCB's master chef can keeps 1,091 at any decimation): its bounding box's 12 edges.
    monkeypatch.setattr(observation, "CLOUD_MAX_EDGES", len(coarse) - 1)
    box = cloud_outline(rock)
    assert box.shape == (12, 2, 3)
    lengths = np.linalg.norm(box[:, 1] - box[:, 0], axis=1)
    assert np.all((lengths > 0.1) & (lengths < 0.11))  # each a side of the box around a rock 0.10-0.108 m across
    mesh = MeshData("rock", rock.vertices.astype(np.float32), rock.faces.astype(np.int32), fine, box)
    assert len(outline_mesh(mesh, cloud=True)[1]) == 12 < len(outline_mesh(mesh)[1])


def test_solids_are_drawn_from_a_decimation_of_a_heavy_scan_and_boxes_as_they_are():
    import trimesh

    from workbench.app.engine.observation import SOLID_FACES, solid_mesh
    from workbench.app.protocol import MeshData

    box = trimesh.creation.box(extents=(0.1, 0.06, 0.02))
    assert solid_mesh(box) is None  # 12 triangles: drawn as they are
    ball = trimesh.creation.icosphere(5, radius=0.05)  # 20,480 faces
    vertices, faces = solid_mesh(ball)
    assert len(faces) <= SOLID_FACES < len(ball.faces)
    assert np.abs(np.linalg.norm(vertices, axis=1) - 0.05).max() < 0.002  # still the ball, within 2 mm
    mesh = MeshData("ball", ball.vertices.astype(np.float32), ball.faces.astype(np.int32), solid=(vertices, faces))
    assert mesh.solid_mesh()[1] is faces and MeshData("box", box.vertices, box.faces).solid_mesh()[1] is box.faces


def test_markdown_escape_keeps_underscores():
    from workbench.app.ui.widgets.markdown import escape

    assert escape("letters, digits, '.', '_' or '-'") == "letters, digits, '.', '\\_' or '-'"
    assert escape("002_master_chef_can") == "002\\_master\\_chef\\_can"


def test_panel_reads_every_field_and_reverts_the_refused_ones():
    import viser

    from workbench.app.ui.reporting import Reporter
    from workbench.app.ui.run.estimator_tab import build_estimator_tab
    from workbench.app.ui.run.status import RunView

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        from workbench.inference.config import EstimatorConfig

        base = EstimatorConfig(particles=128)
        panel = build_estimator_tab(server.gui, base, "robust")
        panel.particles.value = "-5"
        panel.sigma_xy.value = "abc"
        panel.iterations.value = "30"
        config, errors = panel.read_config(base)
        assert set(errors) == {"Particles", "σ x, y (cm)"}, errors
        assert config.particles == 128 and config.sigma == base.sigma and config.iterations == 30
        panel.revert(tuple(errors), config)
        assert panel.particles.value == "128" and panel.sigma_xy.value == "1, 1"
        assert panel.iterations.value == "30"  # a valid field keeps what was typed
        reporter = Reporter(server, RunView)
        reporter.field_errors(errors, panel.field_ids)
        assert panel.particles._impl.uuid in reporter.field_style.content
    finally:
        server.stop()


def test_frame_objects_fits_the_objects_where_known_else_the_region():
    """Bug: on real frames the objects filled a quarter of the view: *Frame objects* framed the whole object
    region. It fits the objects' bounding box (the estimate's, else the ground truth's) and gets closer."""
    from types import SimpleNamespace

    from workbench.app.ui.run.camera import frame_objects
    from workbench.geometry import make_pose

    cube = SimpleNamespace(vertices=np.array([[x, y, z] for x in (-0.03, 0.03) for y in (-0.03, 0.03)
                                              for z in (0.0, 0.06)]))
    sensor = make_pose(np.eye(3), [0.0, -0.8, 0.6])
    view = SimpleNamespace(region=(-0.3, 0.3, -0.3, 0.3), meshes=[cube], T_world_cam=sensor, gt_T_world_obj=None)
    region = frame_objects(view)
    placed = make_pose(np.eye(3), [0.1, 0.05, 0.0])[None]
    fitted = frame_objects(view, placed)

    def distance(pose):
        return np.linalg.norm(np.subtract(pose.position, pose.look_at))

    assert distance(fitted) < 0.5 * distance(region)
    view.gt_T_world_obj = placed  # no estimate yet: the ground truth places the objects
    assert frame_objects(view) == fitted
    view.gt_T_world_obj = np.full((1, 4, 4), np.nan)  # unknown: the region again
    assert frame_objects(view) == region


def test_observed_points_are_sized_by_their_depth():
    from workbench.app.protocol import PointSet
    from workbench.app.ui.run.views import by_depth

    points = np.random.default_rng(0).uniform([-1, -1, 0.5], [1, 1, 2.5], (400, 3)).astype(np.float32)
    bands = by_depth(PointSet(points, np.zeros((400, 3), np.uint8), 0.01), np.eye(4))  # the sensor looks along z
    sizes = [size for _, _, size in bands]
    assert sum(len(p) for p, _, _ in bands) == 400 and sizes == sorted(sizes) and sizes[-1] > 2.5 * sizes[0]
    assert all(np.median(p[:, 2]) * 0.01 / np.median(points[:, 2]) == pytest.approx(s) for p, _, s in bands)


def test_every_table_names_its_objects_beside_their_colour():
    from workbench.app.ui.run.truth import truth_markdown
    from workbench.app.ui.widgets.colors import named, object_color

    row = {"index": 1, "obj_id": 6, "position_cm": 2.7, "rotation_deg": 1.0, "add_s_mm": 3.0, "right": True,
           "confidence": 1.0}
    table = truth_markdown(4, [row], ["wood_block", "foam_brick"])
    assert f"| {named(1, 'foam_brick')} | 2.70 |" in table
    assert "background:rgb({},{},{})".format(*object_color(1)) in named(1, "foam_brick")


def test_a_demo_copied_before_its_models_were_named_gets_their_names(tmp_path):
    import json
    import shutil

    from workbench.app.engine.engine import DEMO_DIR, name_like_bundled

    shutil.copytree(DEMO_DIR, tmp_path / "demo")
    path = tmp_path / "demo" / "models" / "models_info.json"
    bundled = json.loads(path.read_text())
    old = {k: {f: v for f, v in entry.items() if f != "name"} for k, entry in bundled.items()}
    path.write_text(json.dumps(old))
    name_like_bundled(tmp_path / "demo")
    assert json.loads(path.read_text()) == bundled
    path.write_text("{")  # damaged: left to the load to report
    name_like_bundled(tmp_path / "demo")
    assert path.read_text() == "{"
