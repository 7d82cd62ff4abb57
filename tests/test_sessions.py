"""Sessions: a saved run continues bit for bit, and every damaged or unsafe session is refused cleanly."""

import hashlib
import json
import re
import shutil
import subprocess
import sys
import threading
from dataclasses import replace

import numpy as np
import pytest
from PIL import Image

from workbench.errors import InputError
from workbench.evaluation import LocalEvaluator, PoolEvaluator
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator, parse_search
from workbench.inference.smc.particles import Sigma
from workbench.physics import PhysicsConfig
from workbench.problem.build import load_bop_problem
from workbench.problem.problem import ProblemConfig
from workbench.render.depth import RenderConfig
from workbench.render.likelihood import LikelihoodConfig
from workbench.sessions.document import FORMAT_VERSION
from workbench.sessions.store import (
    check_dataset,
    check_name,
    frame_ref_for,
    list_sessions,
    load_session,
    restore_estimator,
    save_session,
    session_problem,
    session_state_from,
    suggest_name,
)

pytestmark = pytest.mark.slow  # needs pybullet and OpenGL

CONFIG = EstimatorConfig(particles=24, seed=11)


@pytest.fixture(scope="module")
def loaded(touching_dataset):
    frame, problem = load_bop_problem(touching_dataset, 0, 0)
    return frame, problem, frame_ref_for(touching_dataset, frame, problem)


def _make_evaluator(kind, problem):
    return LocalEvaluator(problem) if kind == "local" else PoolEvaluator(problem, workers=2)


def _labels(problem):
    return [np.eye(4), None][: problem.n_objects]


def _comparable(history) -> str:
    """The reports without their timings, as text (NaN equals NaN there, and floats show every bit)."""
    return json.dumps([{k: v for k, v in r.as_dict().items() if k != "timings"} for r in history])


@pytest.mark.parametrize("kind,method", [("local", "pipf"), ("local", "mcpf"), ("pool", "pipf")])
def test_resumed_session_steps_bit_identically(loaded, tmp_path, kind, method):
    """Save after iteration 3 (settings changed on the way), restore into a fresh estimator over a problem rebuilt
    from the files and a fresh evaluator, step 3 more: the same as 6 steps without interruption."""
    _, problem, ref = loaded
    evaluator = _make_evaluator(kind, problem)
    try:
        run = Estimator(problem, replace(CONFIG, method=method), evaluator)
        run.step()
        run.set_config(replace(run.config, particles=30, sigma=Sigma(x=0.02, yaw=0.2), data_start=0.5))
        run.step(), run.step(), run.step()
        path = save_session(tmp_path, "run", session_state_from(run, ref, _labels(problem)))
        for _ in range(3):
            run.step()
    finally:
        evaluator.close()

    state = load_session(path)
    assert check_dataset(state) == []
    _, rebuilt = session_problem(state)
    assert check_dataset(state, rebuilt) == []
    evaluator = _make_evaluator(kind, rebuilt)
    try:
        resumed = restore_estimator(state, rebuilt, evaluator)
        assert resumed.iteration == 3 and resumed.config == run.config
        for _ in range(3):
            resumed.step()
    finally:
        evaluator.close()
    for name, array in run.particles.arrays().items():
        assert np.array_equal(getattr(resumed.particles, name), array), name
    assert resumed.rng.bit_generator.state == run.rng.bit_generator.state
    assert (resumed.filter.beta, resumed.filter.calm) == (run.filter.beta, run.filter.calm)
    assert np.array_equal(np.stack(resumed.best_history), np.stack(run.best_history))
    assert _comparable(resumed.history) == _comparable(run.history)
    assert len(state.labels) == 2 and np.array_equal(state.labels[0], np.eye(4)) and state.labels[1] is None


def test_session_before_the_first_step_and_every_setting_roundtrip(loaded, tmp_path):
    _, problem, ref = loaded
    problem_config = ProblemConfig(
        max_render_pixels=4000,
        physics=PhysicsConfig(timestep=1 / 500, max_steps=321, cone_friction=False,
                              shape_overrides=((problem.models[0].obj_id, "convex"),)),
        likelihood=LikelihoodConfig(model="ssd", sigma=0.007, clutter_floor=1.5),
        render=RenderConfig(max_framebuffer=1024, max_depth_error=2e-3))
    config = EstimatorConfig(method="mcpf", particles=24, iterations=9, sigma=Sigma(roll=0.1), state="xyzyaw",
                             seed=3, target_ess=0.5, converge_patience=5)
    fresh = Estimator(replace(problem, config=problem_config), config, evaluator=None)  # never stepped here
    path = save_session(tmp_path, "fresh", session_state_from(fresh, ref, None))
    state = load_session(path)
    assert state.problem_config == problem_config and state.estimator_config == config
    assert state.labels == [None, None] and state.estimator["iteration"] == -1
    assert np.array_equal(state.T_cam_world, problem.camera.T_cam_world) and state.table == problem.table

    _, rebuilt = session_problem(state)
    evaluator = LocalEvaluator(rebuilt)
    try:
        resumed = restore_estimator(state, rebuilt, evaluator)
        direct = Estimator(rebuilt, config, evaluator)
        for _ in range(2):
            resumed.step(), direct.step()
    finally:
        evaluator.close()
    assert np.array_equal(resumed.particles.projected, direct.particles.projected)
    assert np.array_equal(resumed.particles.loglik, direct.particles.loglik)


# ------------------------------------------------------------------------------------------- damaged sessions


@pytest.fixture(scope="module")
def saved(loaded, tmp_path_factory):
    """A valid session of two iterations: folder, JSON file."""
    _, problem, ref = loaded
    folder = tmp_path_factory.mktemp("saved")
    evaluator = LocalEvaluator(problem)
    try:
        estimator = Estimator(problem, CONFIG, evaluator)
        estimator.step(), estimator.step()
    finally:
        evaluator.close()
    return folder, save_session(folder, "base", session_state_from(estimator, ref, _labels(problem)))


def _edit_json(edit):
    def mutate(json_path, npz_path):
        doc = json.loads(json_path.read_text())
        edit(doc)
        json_path.write_text(json.dumps(doc))
    return mutate


def _write_npz_recorded(json_path, npz_path, **arrays):
    """Replace the arrays and record their true size and checksum, as a careful forger would."""
    np.savez(npz_path, **arrays)
    data = npz_path.read_bytes()
    doc = json.loads(json_path.read_text())
    doc["arrays"].update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    json_path.write_text(json.dumps(doc))


def _tamper_npz(json_path, npz_path):
    with np.load(npz_path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["loglik"][0] += 1.0
    np.savez(npz_path, **arrays)


def _pickled_object_array(json_path, npz_path):
    with np.load(npz_path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["loglik"] = np.array([{"payload": 1}] * len(arrays["loglik"]), dtype=object)
    _write_npz_recorded(json_path, npz_path, **arrays)


def _set(keys, value):
    def edit(doc):
        d = doc
        for k in keys[:-1]:
            d = d[k]
        d[keys[-1]] = value
    return _edit_json(edit)


def _add_object(doc):
    doc["frame"]["object_ids"].append(doc["frame"]["object_ids"][0])
    doc["labels"].append(None)


BAD = {
    "corrupt JSON": (lambda j, n: j.write_text('{"format_version": 1, "kind": '), "json", "not JSON"),
    "not a session": (lambda j, n: j.write_text("[1, 2]"), "json", "not a workbench session"),
    "future version": (_set(["format_version"], 99), "json", "newer workbench"),
    "missing entry": (_edit_json(lambda d: d.pop("estimator_config")), "json", "missing entry"),
    "truncated NPZ": (lambda j, n: n.write_bytes(n.read_bytes()[:200]), "npz", "truncated"),
    "tampered NPZ": (_tamper_npz, "npz", "checksum|changed"),
    "missing NPZ": (lambda j, n: n.unlink(), "npz", "not found"),
    "pickled NPZ": (_pickled_object_array, "npz", "unreadable"),
    "object count edited": (_edit_json(_add_object), "json", "array"),
    "history edited": (_edit_json(lambda d: d["estimator"]["history"].pop()), "json", "history"),
    "recorded shape edited": (_set(["arrays", "shapes", "loglik", "shape"], [25]), "json", "records"),
    "labels edited": (_edit_json(lambda d: d["labels"].pop()), "json", "labels"),
    "arrays path escape": (_set(["arrays", "file"], "../base.0123456789abcdef.npz"), "json", "plain file name"),
    "setting type": (_set(["estimator_config", "particles"], "many"), "json", "particles"),
    "setting value": (_set(["problem_config", "physics", "timestep"], -1.0), "json", "timestep"),
    "rng state": (_set(["estimator", "rng", "bit_generator"], "MT19937"), "json", "rng"),
    "estimate out of reach": (_set(["estimator", "search", "map", 1, 0, 3], 1e308), "json", "from the table"),
    "estimate not rigid": (_set(["estimator", "search", "map", 0, 0, 0], 3.0), "json", "rotation|rigid|orthonormal"),
}


LISTED_AS_BROKEN = ("corrupt JSON", "not a session", "future version", "missing entry", "setting type",
                    "setting value", "rng state", "labels edited", "missing NPZ", "arrays path escape")


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("case", list(BAD))
def test_damaged_session_is_refused_and_nothing_changes(saved, tmp_path, case):
    folder, original = saved
    work = tmp_path / "sessions"
    shutil.copytree(folder, work)
    json_path = work / original.name
    npz_path = work / json.loads(json_path.read_text())["arrays"]["file"]
    mutate, blamed, message = BAD[case]
    mutate(json_path, npz_path)
    before = _snapshot(work)
    with pytest.raises(InputError) as err:
        load_session(json_path)
    assert err.value.path == str(json_path if blamed == "json" else npz_path)
    assert re.search(message, err.value.problem), err.value.problem
    assert _snapshot(work) == before
    # The listing reads only the JSON: it flags what the JSON alone shows, and still lists the session.
    listed = {s.name: s for s in list_sessions(work)}
    assert set(listed) == {"base"}
    if case in LISTED_AS_BROKEN:
        assert listed["base"].problem


def _copied(saved, tmp_path):
    """The saved session copied to a folder of its own -> the copy's JSON path."""
    folder, original = saved
    shutil.copytree(folder, tmp_path / "sessions")
    return tmp_path / "sessions" / original.name


def test_format_1_session_loads_with_the_physics_it_ran_with(saved, tmp_path):
    # Format 1 predates PhysicsConfig.sleep_calm: its sessions projected with calm bodies awake.
    json_path = _copied(saved, tmp_path)
    doc = json.loads(json_path.read_text())
    assert doc["format_version"] == FORMAT_VERSION and doc["problem_config"]["physics"]["sleep_calm"] is True
    del doc["problem_config"]["physics"]["sleep_calm"]
    json_path.write_text(json.dumps({**doc, "format_version": 1}))
    assert load_session(json_path).problem_config.physics.sleep_calm is False
    json_path.write_text(json.dumps(doc))  # a format-2 or later file must carry the setting
    with pytest.raises(InputError, match="sleep_calm"):
        load_session(json_path)


def test_format_3_session_loads_without_the_clutter_floor_it_ran_without(saved, tmp_path):
    # Format 3 predates LikelihoodConfig.clutter_floor: its sessions scored unexplained readings as outliers.
    json_path = _copied(saved, tmp_path)
    doc = json.loads(json_path.read_text())
    doc["problem_config"]["likelihood"]["clutter_floor"] = 2.0
    json_path.write_text(json.dumps(doc))
    assert load_session(json_path).problem_config.likelihood.clutter_floor == 2.0
    del doc["problem_config"]["likelihood"]["clutter_floor"]
    json_path.write_text(json.dumps({**doc, "format_version": 3}))
    assert load_session(json_path).problem_config.likelihood.clutter_floor is None
    json_path.write_text(json.dumps(doc))  # a format-4 file must carry the setting
    with pytest.raises(InputError, match="clutter_floor"):
        load_session(json_path)
    doc["problem_config"]["likelihood"]["clutter_floor"] = "high"
    json_path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="clutter_floor"):
        load_session(json_path)


def test_format_4_session_loads_with_the_floor_weighed_in_from_the_start(saved, tmp_path):
    # Format 4 predates EstimatorConfig.floor_from: its sessions weighed the clutter floor in from the start.
    json_path = _copied(saved, tmp_path)
    doc = json.loads(json_path.read_text())
    assert doc["estimator_config"]["floor_from"] == 0.5 and doc["estimator"]["search"]["floor_in"] in (True, False)
    del doc["estimator_config"]["floor_from"]
    del doc["estimator"]["search"]["floor_in"]
    json_path.write_text(json.dumps({**doc, "format_version": 4}))
    state = load_session(json_path)
    assert state.estimator_config.floor_from == 0.0
    assert parse_search(state.estimator["search"], len(state.frame.object_ids))["floor_in"] is False  # rescored
    json_path.write_text(json.dumps(doc))  # a format-5 file must carry the setting
    with pytest.raises(InputError, match="floor_from"):
        load_session(json_path)
    doc["estimator_config"]["floor_from"] = 0.5
    doc["estimator"]["search"]["floor_in"] = "yes"
    json_path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="floor_in"):
        load_session(json_path)


# Format 6 predates EstimatorConfig.leaning: its sessions searched without leaning starts. Format 8 predates
# EstimatorConfig.floor_calm: its sessions weighed the clutter floor in at floor_from only.
@pytest.mark.parametrize("version, name, today, then, bad", [(6, "leaning", True, False, ()),
                                                             (8, "floor_calm", 3, None, (0, "3", 2.5))])
def test_an_older_session_loads_with_the_estimator_setting_it_ran_with(saved, tmp_path, version, name, today, then,
                                                                       bad):
    json_path = _copied(saved, tmp_path)
    doc = json.loads(json_path.read_text())
    assert doc["estimator_config"][name] == today  # today's default
    del doc["estimator_config"][name]
    json_path.write_text(json.dumps({**doc, "format_version": version}))
    assert getattr(load_session(json_path).estimator_config, name) == then
    json_path.write_text(json.dumps(doc))  # a file of the next format must carry the setting
    with pytest.raises(InputError, match=name):
        load_session(json_path)
    for value in bad:
        json_path.write_text(json.dumps({**doc, "estimator_config": {**doc["estimator_config"], name: value}}))
        with pytest.raises(InputError, match=name):
            load_session(json_path)


def test_format_7_session_loads_with_bullet_and_a_bad_backend_is_refused(saved, tmp_path):
    # Format 7 predates PhysicsConfig.backend: its sessions projected in Bullet.
    json_path = _copied(saved, tmp_path)
    doc = json.loads(json_path.read_text())
    doc["problem_config"]["physics"]["backend"] = "mujoco"
    json_path.write_text(json.dumps(doc))
    assert load_session(json_path).problem_config.physics.backend == "mujoco"
    del doc["problem_config"]["physics"]["backend"]
    json_path.write_text(json.dumps({**doc, "format_version": 7}))
    assert load_session(json_path).problem_config.physics.backend == "pybullet"
    json_path.write_text(json.dumps(doc))  # a format-8 file must carry the setting
    with pytest.raises(InputError, match="backend"):
        load_session(json_path)
    json_path.write_text(json.dumps({**doc, "problem_config": {**doc["problem_config"], "physics": {
        **doc["problem_config"]["physics"], "backend": "havok"}}}))
    with pytest.raises(InputError, match="backend.*pybullet, mujoco"):
        load_session(json_path)


def test_serve_refuses_a_mujoco_session_without_mujoco_and_physics_beside_a_session(saved, tmp_path, monkeypatch,
                                                                                    capsys):
    from workbench.cli import main

    json_path = _copied(saved, tmp_path)
    assert main(["serve", "--session", str(json_path), "--physics", "mujoco", "--port", "1"]) == 2
    assert "--session: a session brings its own run settings: give no --physics" in capsys.readouterr().err
    doc = json.loads(json_path.read_text())
    doc["problem_config"]["physics"]["backend"] = "mujoco"
    json_path.write_text(json.dumps(doc))
    monkeypatch.setitem(sys.modules, "mujoco", None)  # `import mujoco` now fails as where it is not installed
    assert main(["serve", "--session", str(json_path), "--port", "1"]) == 2
    assert "--physics: mujoco is not installed" in capsys.readouterr().err


def test_format_5_session_is_scored_again_by_todays_clutter_floor(saved, loaded, tmp_path):
    # Format 5 scored a reading an object claims on unclaimed clutter by an older rule: restored, the particles and
    # the estimate are scored again before they compete with new hypotheses.
    _, problem, _ = loaded
    json_path = _copied(saved, tmp_path)
    doc = json.loads(json_path.read_text())
    doc["estimator"]["search"]["floor_in"] = True
    json_path.write_text(json.dumps({**doc, "format_version": 5}))
    state = load_session(json_path)
    evaluator = LocalEvaluator(problem)
    try:
        restored = restore_estimator(state, problem, evaluator)
        assert restored.filter.floor_in is False
        restored.particles.loglik[:] -= 100.0  # as if scored by another rule
        restored.filter.weigh_floor_in()
        ok = np.isfinite(restored.particles.loglik)
        again = evaluator.evaluate(restored.particles.projected[ok], project=False).loglik
        assert ok.any() and np.allclose(restored.particles.loglik[ok], again)
    finally:
        evaluator.close()
    json_path.write_text(json.dumps({**doc, "format_version": FORMAT_VERSION}))  # today's format: as saved
    assert load_session(json_path).estimator["search"]["floor_in"] is True


@pytest.mark.parametrize("version", [2, 5])
def test_an_older_session_without_its_estimator_state_is_refused_by_name(saved, tmp_path, version):
    # The format upgrades read estimator.search before the document is checked: a malformed entry there must end
    # in the same clear error as in today's format, not a crash.
    json_path = _copied(saved, tmp_path)
    doc = json.loads(json_path.read_text())
    json_path.write_text(json.dumps({**doc, "estimator": None, "format_version": version}))
    with pytest.raises(InputError) as err:
        load_session(json_path)
    assert err.value.path == str(json_path) and "malformed" in err.value.problem


def test_format_2_session_loads_its_move_kinds_from_the_json(saved, tmp_path):
    # Format 2 kept each particle's move kind in the JSON (estimator.search.kinds), not in the arrays file.
    folder, original = saved
    work = tmp_path / "sessions"
    shutil.copytree(folder, work)
    json_path = work / original.name
    npz_path = work / json.loads(json_path.read_text())["arrays"]["file"]
    with np.load(npz_path) as z:
        arrays = {k: z[k] for k in z.files}
    kinds = arrays.pop("kinds")
    assert len(set(kinds.tolist())) > 1  # a run of the default search: several kinds to carry over

    def as_format_2(doc):
        doc["format_version"] = 2
        doc["estimator"]["search"]["kinds"] = kinds.tolist()
        del doc["arrays"]["shapes"]["kinds"]
    _edit_json(as_format_2)(json_path, npz_path)
    _write_npz_recorded(json_path, npz_path, **arrays)
    assert np.array_equal(load_session(json_path).estimator["particles"].kinds, kinds)

    _edit_json(lambda doc: doc["estimator"]["search"].update(kinds=[99] * len(kinds)))(json_path, npz_path)
    with pytest.raises(InputError, match="unknown move kinds"):
        load_session(json_path)


@pytest.mark.parametrize("name", ["../../etc/x", "a/b", "..", ".hidden", "-x", "", "x" * 65, "naïve", "a b"])
def test_unsafe_names_are_refused_and_nothing_is_written(saved, tmp_path, name):
    folder, original = saved
    state = load_session(original)
    target = tmp_path / "deep" / "er" / "sessions"
    with pytest.raises(InputError, match="not a valid session name"):
        save_session(target, name, state)
    assert not (tmp_path / "deep").exists()
    assert check_name(suggest_name(name)) == suggest_name(name)


def test_suggested_names():
    assert suggest_name("../../etc/x") == "etc-x"
    assert suggest_name("my run #2") == "my-run-2"
    assert suggest_name("...") == "session"
    assert check_name("run-1_v2.final") == "run-1_v2.final"


def test_existing_session_is_replaced_only_when_asked(saved, tmp_path, loaded):
    folder, original = saved
    work = tmp_path / "sessions"
    shutil.copytree(folder, work)
    state = load_session(work / original.name)
    changed = replace(state, labels=[np.eye(4), np.eye(4)])
    before = _snapshot(work)
    with pytest.raises(InputError, match="exists") as err:
        save_session(work, "base", changed)
    assert err.value.path == str(work / "base.json")
    assert _snapshot(work) == before

    save_session(work, "base", changed, overwrite=True)
    assert [p.name for p in work.glob("*.npz")] == [json.loads((work / "base.json").read_text())["arrays"]["file"]]
    assert all(T is not None for T in load_session(work / "base.json").labels)

    save_session(work, "other", state)
    infos = list_sessions(work)
    assert sorted(s.name for s in infos) == ["base", "other"]
    assert all(s.problem is None and s.iteration == 1 and s.particles == 24 for s in infos)


def test_two_writers_of_one_folder_never_both_save_a_new_name(saved, tmp_path):
    """Two `serve` on one --sessions-dir saving one name at once: both said "Saved" and the first was replaced
    without *Replace*. Another process holds the folder while it saves that name; our save waits, then sees the
    session and is refused instead of replacing it."""
    folder, original = saved
    work = tmp_path / "sessions"
    shutil.copytree(folder, work)
    state = load_session(work / original.name)
    other = subprocess.Popen(
        [sys.executable, "-c", "import shutil, sys; from workbench.io.outputs import folder_lock\n"
                               f"with folder_lock({str(work)!r}):\n"
                               "    print('locked', flush=True); sys.stdin.readline()\n"
                               f"    shutil.copy({str(original)!r}, {str(work / 'new.json')!r})"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    outcome = {}

    def save():
        try:
            outcome["path"] = save_session(work, "new", state)
        except InputError as err:
            outcome["error"] = err

    try:
        assert other.stdout.readline().strip() == "locked"
        saver = threading.Thread(target=save)
        saver.start()
        saver.join(0.5)
        assert saver.is_alive() and not outcome  # waiting for the other writer, nothing written
        other.stdin.write("go\n")
        other.stdin.flush()
        saver.join(60)
    finally:
        other.kill() if other.poll() is None else None
        other.wait()
    assert "exists" in outcome["error"].problem
    assert (work / "new.json").read_bytes() == original.read_bytes()


def test_changed_or_missing_dataset_files_are_reported(touching_dataset, tmp_path):
    dataset = tmp_path / "dataset"
    shutil.copytree(touching_dataset, dataset)
    frame, problem = load_bop_problem(dataset, 0, 0)
    state = session_state_from(Estimator(problem, CONFIG, evaluator=None), frame_ref_for(dataset, frame, problem),
                               None)
    assert check_dataset(state) == []

    depth_path = dataset / "test" / "000000" / "depth" / "000000.png"
    depth = np.asarray(Image.open(depth_path))
    Image.fromarray((depth + (depth > 0) * 3).astype(np.uint16)).save(depth_path)  # 0.3 mm further everywhere
    mesh = dataset / "models" / f"obj_{frame.object_ids[1]:06d}.ply"
    mesh.unlink()
    problems = check_dataset(state)
    assert problems == [f"{depth_path}: changed since the session was saved", f"{mesh}: missing"]

    mesh.write_bytes((touching_dataset / "models" / mesh.name).read_bytes())
    _, rebuilt = session_problem(state)
    assert check_dataset(state, rebuilt)[-1].startswith("the rebuilt problem differs")


# ----------------------------------------------------------------------------------------------------------------
# The settled answer and its posterior: saved with the run, shown again on load without settling


@pytest.fixture(scope="module")
def settled(loaded, tmp_path_factory):
    """A session saved right after settling (its posterior current): folder, JSON file, the estimator saved."""
    _, problem, ref = loaded
    folder = tmp_path_factory.mktemp("settled")
    evaluator = LocalEvaluator(problem)
    try:
        estimator = Estimator(problem, CONFIG, evaluator)
        estimator.step(), estimator.step()
        estimator.settle()
    finally:
        evaluator.close()
    assert estimator.current_posterior is not None
    return folder, save_session(folder, "settled", session_state_from(estimator, ref, _labels(problem))), estimator


def test_a_settled_session_restores_its_posterior_exactly(settled, loaded):
    _, path, saved_run = settled
    _, problem, _ = loaded
    state = load_session(path)
    evaluator = LocalEvaluator(problem)
    try:
        restored = restore_estimator(state, problem, evaluator)
        before = restored.settle_scenes
        assert restored.answer_current and np.array_equal(restored.settle(), saved_run.settled)
        assert restored.settle_scenes == before  # the saved answer is the current one: nothing settled again
    finally:
        evaluator.close()
    assert restored.settled_loglik == saved_run.settled_loglik
    assert [(t.obj, t.turn, t.gap) for t in restored.ties] == [(t.obj, t.turn, t.gap) for t in saved_run.ties]
    a, b = saved_run.posterior, restored.current_posterior
    assert a.temperature == b.temperature and len(a.objects) == len(b.objects) == problem.n_objects
    for x, y in zip(a.objects, b.objects):
        assert (x.obj, x.position_spread_m, x.yaw_range_deg, x.seen_through, x.elsewhere) == \
            (y.obj, y.position_spread_m, y.yaw_range_deg, y.seen_through, y.elsewhere)
        assert len(x.modes) == len(y.modes)
        for m, n in zip(x.modes, y.modes):
            assert np.array_equal(m.T, n.T) and (m.loglik, m.gap, m.probability, m.what) == \
                (n.loglik, n.gap, n.probability, n.what)


def test_a_posterior_saved_before_elsewhere_was_reported_loads_without_doubt(settled, loaded, tmp_path):
    folder, original, _ = settled
    work = tmp_path / "sessions"
    shutil.copytree(folder, work)
    json_path = work / original.name
    doc = json.loads(json_path.read_text())
    for o in doc["estimator"]["answer"]["posterior"]["objects"]:  # as an older version wrote it
        del o["seen_through"], o["elsewhere"]
    json_path.write_text(json.dumps(doc))
    _, problem, _ = loaded
    evaluator = LocalEvaluator(problem)
    try:
        old = restore_estimator(load_session(json_path), problem, evaluator)
    finally:
        evaluator.close()
    assert all(o.elsewhere == 0.0 and o.seen_through == 0.0 for o in old.current_posterior.objects)
    assert all(np.isclose(sum(m.probability for m in o.modes), 1.0) for o in old.current_posterior.objects)


def test_a_stale_or_missing_answer_loads_as_no_posterior(saved, settled, loaded, tmp_path):
    """A run stepped on after settling saves no answer (its posterior was of an older estimate); a session saved
    before answers were kept (no ``answer`` entry) loads with none."""
    _, problem, ref = loaded
    run = settled[2]
    evaluator = LocalEvaluator(problem)
    try:
        stepped = restore_estimator(load_session(settled[1]), problem, evaluator)
        assert stepped.current_posterior is not None
        # A step that finds no better scene leaves the estimate, and so its answer, as it was: step until it moves
        # (how many steps that takes depends on the platform's floating point, not on what is tested here).
        for _ in range(10):
            stepped.step()
            if not np.array_equal(stepped.filter.estimate, run.filter.estimate):
                break
        assert not np.array_equal(stepped.filter.estimate, run.filter.estimate), "ten steps never moved the estimate"
        assert stepped.current_posterior is None
        path = save_session(tmp_path, "stepped", session_state_from(stepped, ref, _labels(problem)))
        assert json.loads(path.read_text())["estimator"]["answer"] is None
        assert load_session(path).estimator["answer"] is None
        work = tmp_path / "old"
        shutil.copytree(saved[0], work)
        json_path = work / saved[1].name
        doc = json.loads(json_path.read_text())
        del doc["estimator"]["answer"]
        json_path.write_text(json.dumps(doc))
        old = restore_estimator(load_session(json_path), problem, evaluator)
        assert old.current_posterior is None and old.posterior is None and not old.answer_current
    finally:
        evaluator.close()
    assert run.current_posterior is not None


def _answer_edit(edit):
    return _edit_json(lambda doc: edit(doc["estimator"]["answer"]))


BAD_ANSWERS = {
    "not an object": (_set(["estimator", "answer"], [1, 2]), r"estimator\.answer must be an object"),
    "probability over 1": (_answer_edit(lambda a: a["posterior"]["objects"][0]["modes"][0].update(probability=1.5)),
                           r"answer\.posterior\.objects\[0\]\.modes\[0\]\.probability"),
    "probabilities do not sum to 1": (
        _answer_edit(lambda a: a["posterior"]["objects"][0]["modes"].append(
            {**a["posterior"]["objects"][0]["modes"][0], "probability": 0.5})),
        r"answer\.posterior\.objects\[0\]\.modes must be probabilities"),
    "mode pose a reflection": (
        _answer_edit(lambda a: a["posterior"]["objects"][1]["modes"][0]["T"].__setitem__(0, [-1.0, 0.0, 0.0, 0.0])),
        r"answer\.posterior\.objects\[1\]\.modes\[0\]\.T"),
    "object missing": (_answer_edit(lambda a: a["posterior"]["objects"].pop()),
                       r"answer\.posterior\.objects must list the 2 objects"),
    "what not text": (_answer_edit(lambda a: a["posterior"]["objects"][0]["modes"][0].update(what=3)),
                      r"modes\[0\]\.what must be a short text"),
    "yaw range": (_answer_edit(lambda a: a["posterior"]["objects"][0].update(yaw_range_deg=[10.0, 5.0])),
                  r"yaw_range_deg"),
    "temperature": (_answer_edit(lambda a: a["posterior"].update(temperature=-1.0)), r"temperature must be > 0"),
    "elsewhere over 1": (_answer_edit(lambda a: a["posterior"]["objects"][0].update(elsewhere=1.5)),
                         r"objects\[0\]\.elsewhere and \.seen_through must lie in \[0, 1\]"),
    "elsewhere without seen_through": (_answer_edit(lambda a: a["posterior"]["objects"][0].pop("seen_through")),
                                       r"objects\[0\] must have exactly the entries"),
    "spread NaN": (_answer_edit(lambda a: a["posterior"]["objects"][0].update(position_spread_m=float("nan"))),
                   r"position_spread_m must be a finite number"),
    "no estimate": (_set(["estimator", "search", "map"], None), r"answer.*without an estimate"),
}


@pytest.mark.parametrize("case", list(BAD_ANSWERS))
def test_a_damaged_posterior_is_refused_naming_the_file(settled, tmp_path, case):
    folder, original, _ = settled
    work = tmp_path / "sessions"
    shutil.copytree(folder, work)
    json_path = work / original.name
    npz_path = work / json.loads(json_path.read_text())["arrays"]["file"]
    mutate, message = BAD_ANSWERS[case]
    mutate(json_path, npz_path)
    with pytest.raises(InputError) as err:
        load_session(json_path)
    assert err.value.path == str(json_path)
    assert re.search(message, err.value.problem), err.value.problem
