"""The engine: owns the problem and the ``Estimator`` of the estimator process, and answers the server's commands.

It runs in a process of its own (``engine_process``) so that the browser server never waits for an iteration.
Commands are drained between iterations, so a Pause takes effect after the iteration in progress. A run starts an
iteration only once the server has shown the last one (``protocol.Shown``): a slow display holds the run back
instead of falling behind it, and a Pause stops the run one iteration after the one on display at the latest.

Labels, sessions and sequences are handled in this process too, because they need the estimator and a renderer:
the server only shows them (``engine_labels``, ``engine_sessions``, ``engine_sequence``).

A dead evaluation worker surfaces as ``WorkerCrashed`` (or a broken pipe): the pool is rebuilt and the iteration
retried once, and the user is told (``evaluators``). If this whole process dies, ``engine_process.EngineClient``
(the server side) restarts it and reloads the frame.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import traceback
from dataclasses import replace
from pathlib import Path
from typing import Callable

from workbench.app import protocol as p
from workbench.app.engine import label_files
from workbench.app.engine.evaluators import CRASH_ERRORS, Evaluators
from workbench.app.engine.label_sequence import SequenceLabelling
from workbench.app.engine.labels import FrameLabels
from workbench.app.engine.on_show import RunOnShow
from workbench.app.engine.sequence import EngineSequence, HeldRun
from workbench.app.engine.sessions import OpenedSession, open_session, save_session
from workbench.app.engine.snapshot import ParticleDisplay
from workbench.errors import InputError
from workbench.io.readers import read_json
from workbench.physics.config import PhysicsConfig

log = logging.getLogger(__name__)

SEQUENCE_LABEL_COMMANDS = (p.CheckSequenceLabels, p.PropagateLabel, p.EndSequenceLabel, p.FitSequenceLabels,
                           p.SaveSequenceLabels, p.ShowLabelledFrame)
DEMO_DIR = Path(__file__).resolve().parents[3] / "assets" / "demo"


# ---------------------------------------------------------------------------------------------------------------
# Loading


def user_data_dir() -> Path:
    """Where the workbench keeps what a user may change: ``$WORKBENCH_HOME``, else ``$XDG_DATA_HOME/workbench``,
    else ``~/.local/share/workbench``."""
    if os.environ.get("WORKBENCH_HOME"):
        return Path(os.environ["WORKBENCH_HOME"]).expanduser()
    base = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(base).expanduser() / "workbench"


def name_like_bundled(demo: Path) -> None:
    """Give a demo copied before the bundled models were named (``obj_000006``) their names; nothing else of the
    copy changes. A copy that cannot be read is left to the load, which says what is wrong with it."""
    bundled, copied = DEMO_DIR / "models" / "models_info.json", demo / "models" / "models_info.json"
    try:
        names = {k: v["name"] for k, v in read_json(bundled).items() if "name" in v}
        info = read_json(copied)  # the one reader: a copy nested 200,000 levels deep is refused, not a RecursionError
    except (ValueError, AttributeError, TypeError):  # InputError among them
        return
    missing = {k: n for k, n in names.items() if isinstance(info.get(k), dict) and "name" not in info[k]}
    if missing:
        info.update({k: {"name": n, **info[k]} for k, n in missing.items()})
        copied.write_text(json.dumps(info, indent=2) + "\n")


def demo_dataset() -> Path:
    """The demo the app shows, and saves labels into: ``user_data_dir()/demo``, copied once from the bundled
    ``assets/demo`` (or written by ``synth.make_demo`` when the checkout has none), so that nothing is ever saved
    into the installed package. An existing copy is used as it is: it may hold the user's labels."""
    out = user_data_dir() / "demo"
    if (out / "models" / "models_info.json").is_file():
        name_like_bundled(out)
        return out
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out, "the demo's copy is incomplete (no models/models_info.json): move it away and the "
                              "demo is copied again")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".demo-", dir=out.parent))  # copied whole, then renamed into place
    try:
        if (DEMO_DIR / "models").is_dir():
            shutil.copytree(DEMO_DIR, tmp, dirs_exist_ok=True)
        else:
            from workbench.synth import make_demo

            make_demo(tmp)
        os.replace(tmp, out)  # onto a missing or empty folder
    except OSError:
        if not (out / "models" / "models_info.json").is_file():  # not another engine's copy, finished first
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log.info("copied the demo to %s", out)
    return out


def load(source: p.Source, likelihood: str, physics: PhysicsConfig = PhysicsConfig()):
    """-> (dataset folder, frame, problem, the frame's view) for ``source``; raises ``InputError`` naming the file at
    fault."""
    from workbench.app.engine.observation import build_view
    from workbench.io import bop
    from workbench.problem.build import load_bop_problem
    from workbench.problem.problem import ProblemConfig
    from workbench.render.likelihood import LikelihoodConfig

    dataset = demo_dataset() if source.demo else source.dataset
    if dataset is None:
        raise InputError(None, "no dataset given: type a BOP dataset folder or load the demo")
    dataset = Path(dataset).expanduser()
    if not dataset.exists():
        raise InputError(dataset, "no such file or folder")
    scene_id, im_id = source.scene_id, source.im_id
    if scene_id is None or im_id is None:
        frames = [f for f in bop.list_frames(dataset) if scene_id is None or f[0] == scene_id]
        if not frames:
            raise InputError(dataset, f"no frames{'' if scene_id is None else f' in scene {scene_id}'}")
        scene_id, im_id = frames[0] if im_id is None else (frames[0][0], im_id)
    config = ProblemConfig(likelihood=LikelihoodConfig(model=likelihood), physics=physics)
    frame, problem = load_bop_problem(dataset, scene_id, im_id, config=config)
    return dataset, frame, problem, build_view(frame, problem, source.title(frame.scene_id, frame.im_id), dataset)


def with_likelihood(problem, likelihood: str):
    """``problem`` with the likelihood model ``likelihood`` (checked)."""
    likelihood_config = replace(problem.config.likelihood, model=likelihood)
    likelihood_config.validate()
    return replace(problem, config=replace(problem.config, likelihood=likelihood_config))


def session_source(dataset: Path, split: str | None, frame) -> p.Source:
    """What a restarted engine reloads for a session's frame of ``dataset`` (its ``split`` folder, if any): the
    demo when the session was saved from the demo's copy or the bundled folder."""
    if dataset.resolve() in (DEMO_DIR, user_data_dir().resolve() / "demo"):
        return p.Source(demo=True)
    return p.Source(dataset / split if split else dataset, frame.scene_id, frame.im_id)


def prepare_session(cmd: p.LoadSession) -> tuple[OpenedSession, p.Source, p.ObservationView] | p.SessionQuestion:
    """The session ``cmd`` names, with what a restarted engine reloads for its frame and that frame's view, or the
    question to ask first (``sessions.open_session``). Touches nothing of the current run."""
    from workbench.app.engine.observation import build_view

    opened = open_session(Path(cmd.path), cmd.confirmed)
    if isinstance(opened, p.SessionQuestion):
        return opened
    source = session_source(opened.dataset, opened.state.frame.split, opened.frame)
    return opened, source, build_view(opened.frame, opened.problem, opened.title(), opened.dataset)


def stage_reporter(results, estimator) -> Callable[[str], None]:
    """``StageClock.on_stage`` for a run in the workbench: each stage the run enters, told to the server."""
    return lambda name: results.put(p.Stage(name, estimator.clock.elapsed()))


def nothing_to_run(est) -> p.Failure:
    """What a Run on the finished run ``est`` is told."""
    return p.Failure("Nothing to run", f"the run is at iteration {est.iteration} of {est.config.iterations}"
                                       + (" and has converged" if est.converged else "")
                                       + ": raise the iteration budget, press Step, or Reset")


# ---------------------------------------------------------------------------------------------------------------
# The engine


class Engine:
    """One estimation run on the loaded frame, answering the server's commands (``handle``). Its collaborators:
    ``evaluators`` (the worker pool and an in-process renderer), ``display`` (what of the run is shown), ``labels``
    (the frame's labels) and ``sequence`` (the frames of its scene). These get only what they use (``on_show``: the
    run on show, read-only) and change none of the engine's fields: it applies what they return (``put_on_show``)."""

    def __init__(self, results, workers: int, ray=None, physics: PhysicsConfig = PhysicsConfig()):
        # results: what the engine tells the server, anything with a put (engine_process.Outbox, a test's list)
        self.results = results
        self.physics = physics  # how the frames it loads are simulated (a session brings its own)
        self.evaluators = Evaluators(results, workers, ray)
        self.display = ParticleDisplay()
        self.labels = FrameLabels(results, self.evaluators, self.on_show)
        self.sequence = EngineSequence(results, self.evaluators, self.on_show, self.pause)
        self.sequence_labels = SequenceLabelling(results, self.labels, self.sequence, self.on_show)
        self.problem = self.frame = self.estimator = self.config = None
        self.running = False
        self.unshown: int | None = None  # the iteration last published and not yet Shown by the server
        self.stop_on_convergence = True

    # -- commands

    def handle(self, cmd) -> None:
        if isinstance(cmd, p.Load):
            self.load(cmd)
        elif isinstance(cmd, p.Reset):
            self.reset(cmd.config, cmd.likelihood)
        elif isinstance(cmd, p.SetConfig):
            self.set_config(cmd.config)
        elif isinstance(cmd, p.Select):
            self.display.rank = max(0, int(cmd.rank))
            self.publish_chosen()
        elif isinstance(cmd, p.SetDisplay):
            self.display.max_display = max(1, int(cmd.max_particles))
            if self.estimator is not None and self.estimator.particles is not None:
                self.publish()
        elif isinstance(cmd, p.Step):
            if not self.running:
                self.step()
        elif isinstance(cmd, p.Run):
            self.start(cmd.stop_on_convergence)
        elif isinstance(cmd, p.Shown):
            if self.unshown is not None and cmd.iteration >= self.unshown:
                self.unshown = None
        elif isinstance(cmd, p.Pause):
            self.pause()
        elif isinstance(cmd, p.SetLabels):
            self.labels.set(cmd)
        elif isinstance(cmd, (p.SnapLabels, p.FitLabels)):
            self.aside("labels", self.labels.snap if isinstance(cmd, p.SnapLabels) else self.labels.fit)
        elif isinstance(cmd, p.UseBestAsLabel):
            self.aside("labels", lambda: self.labels.use_best(cmd.modes, cmd.iteration) and self.publish())
        elif isinstance(cmd, (p.SaveLabels, p.ListBackups, p.RestoreBackup)):
            self.aside("labels", lambda: self.reload_truth(label_files.act(cmd, self.labels, self.on_show())))
        elif isinstance(cmd, p.SaveSession):
            self.aside("session", lambda: self.save_session(cmd))
        elif isinstance(cmd, p.LoadSession):
            self.aside("session", lambda: self.load_session(cmd))
        elif isinstance(cmd, p.NextFrame):
            self.sequence.guarded(lambda: self.put_on_show(self.sequence.next()))
        elif isinstance(cmd, p.ShowFrame):
            self.sequence.guarded(lambda: self.put_on_show(self.sequence.show(cmd.im_id)))
        elif isinstance(cmd, SEQUENCE_LABEL_COMMANDS):
            self.sequence_labels_command(cmd)

    def sequence_labels_command(self, cmd) -> None:
        """A command of the sequence's labels (``label_sequence``): a Run is paused first, as Next pauses it, since
        showing another frame replaces the run and a fit holds the engine for a while. Done is said in any case:
        the folder's buttons wait for it."""
        self.pause()
        s = self.sequence_labels
        try:
            if isinstance(cmd, p.ShowLabelledFrame):
                s.guarded(lambda: self.put_on_show(s.held_for(cmd.im_id)))
            elif isinstance(cmd, p.SaveSequenceLabels):
                s.guarded(lambda: self.reload_truth(s.save(cmd)))
            else:
                act = {p.CheckSequenceLabels: s.check, p.PropagateLabel: s.propagate, p.EndSequenceLabel: s.end}
                s.guarded(lambda: act[type(cmd)](cmd) if type(cmd) in act else s.fit())
        finally:
            self.results.put(p.SequenceLabelsDone())

    def on_show(self) -> RunOnShow:
        """The run on show, read-only, as the helpers (``labels``, ``sequence``) see it."""
        return RunOnShow(self.frame, self.problem, self.estimator, self.config, self.running, self.stop_on_convergence)

    def aside(self, topic: str, action: Callable[[], None]) -> None:
        """A labelling or session action: bad input is reported next to its button and the run goes on (``fail``
        would stop it)."""
        try:
            action()
        except InputError as err:
            self.results.put(p.Failure(f"{topic.capitalize()}: not done", err.problem, err.path, topic=topic))

    def load(self, cmd: p.Load) -> None:
        cmd.config.validate()
        self.sequence_labels.refuse_to_drop()
        dataset, frame, problem, view = load(cmd.source, cmd.likelihood, self.physics)  # on failure the old run stays
        self.replace_frame(cmd.source, view, frame, problem, cmd.config)
        self.new_estimator()
        self.labels.adopt_frame(dataset)
        self.sequence.start(cmd.source, dataset, None, view)
        self.sequence_labels.forget()

    def replace_frame(self, source: p.Source, view: p.ObservationView, frame, problem, config) -> None:
        """Put ``frame`` in place of the loaded one and show it; the run on it is started by the caller."""
        self.running = False
        self.evaluators.use(problem)
        self.frame, self.problem, self.config = frame, problem, config
        self.display.forget()
        self.results.put(p.Loaded(source, view))

    def reset(self, config, likelihood: str) -> None:
        if self.problem is None:
            raise InputError(None, "nothing is loaded: load a dataset or the demo first")
        config.validate()
        self.config = config
        if likelihood != self.problem.config.likelihood.model:
            self.problem = with_likelihood(self.problem, likelihood)
            self.evaluators.use(self.problem)
        self.new_estimator()

    def set_config(self, config) -> None:
        config.validate()
        self.config = config
        if self.estimator is not None:
            self.estimator.set_config(config)

    def new_estimator(self) -> None:
        from workbench.inference.estimator import Estimator

        self.running = False
        self.unshown = None  # a snapshot of the old run still on its way does not hold up the new one
        self.estimator = Estimator(self.problem, self.config, self.evaluators.evaluator())
        self.display.forget()
        self.labels.reference = None
        self.send_state("reset")

    # -- running

    def start(self, stop_on_convergence: bool) -> None:
        if self.estimator is None:
            raise InputError(None, "nothing is loaded: load a dataset or the demo first")
        self.stop_on_convergence = stop_on_convergence
        if self.finished():
            self.results.put(nothing_to_run(self.estimator))
            return
        # Each Run has the whole budget (EstimatorConfig.budget_s) to itself, and says which stage it is in.
        self.estimator.start_clock(on_stage=stage_reporter(self.results, self.estimator))
        self.running = True
        self.send_state("running")

    def pause(self) -> None:
        if self.running:
            self.running = False
            self.send_state("paused")

    def may_step(self) -> bool:
        """Running, and the server shows the last iteration (see ``protocol.Shown``)."""
        return self.running and self.unshown is None

    def finished(self) -> bool:
        """At the run's own budget (a tracked frame's is its short search's), or converged."""
        est = self.estimator
        return est.iteration >= est.config.iterations or (self.stop_on_convergence and est.iteration >= 0
                                                          and est.converged)

    def step(self) -> None:
        from workbench.evaluation import WorkerCrashed

        if self.estimator is None:
            raise InputError(None, "nothing is loaded: load a dataset or the demo first")
        if not self.running:  # a Step is a run of its own: the cuts of the Run before it no longer stand
            self.estimator.start_clock(on_stage=stage_reporter(self.results, self.estimator))
        try:
            report = self.estimator.step()
        except (WorkerCrashed, *CRASH_ERRORS) as err:
            self.estimator.evaluator = self.evaluators.restart(err)
            report = self.estimator.step()  # a second crash in a row is a Failure for the user
        out_of_time = self.running and self.estimator.out_of_budget()
        if self.running and (self.finished() or out_of_time):
            self.running = False
        if self.finished() or out_of_time:
            # The run's answer, as `workbench estimate` gives it: the estimate settled, with its posterior, which
            # the snapshot carries. Computed once per estimate (a Step past the end settles only a new one).
            self.estimator.settle()
        self.publish(report)
        if self.finished():
            self.sequence.finished()
        else:
            self.sequence.stepped()
        if not self.running:
            self.send_state("converged" if report.converged else "done" if self.finished()
                            else "budget spent" if out_of_time else "paused")

    def publish(self, report=None) -> None:
        est = self.estimator
        if report is None:
            if not est.history:
                return
            report = est.history[-1]
        self.results.put(self.display.snapshot(est, report, self.running, self.config.particles,
                                               self.labels.reference_loglik()))
        self.unshown = est.iteration
        self.publish_chosen()
        self.labels.publish_errors()
        self.labels.publish_truth()

    def publish_chosen(self) -> None:
        chosen = None if self.estimator is None else self.display.chosen(self.estimator, self.evaluators.explain)
        if chosen is not None:
            self.results.put(chosen)

    def send_state(self, reason: str) -> None:
        self.results.put(p.RunState(self.running, -1 if self.estimator is None else self.estimator.iteration, reason))

    def fail(self, err: BaseException) -> None:
        """Tell the user; stop running; keep serving."""
        self.running = False
        if isinstance(err, InputError):
            self.results.put(p.Failure("Input error", err.problem, err.path))
        else:
            log.error("engine error\n%s", traceback.format_exc())
            self.results.put(p.Failure(f"Estimator error ({type(err).__name__})", str(err) or repr(err)))
        self.send_state("error")

    # -- sequences and sessions

    def reload_truth(self, frame) -> None:
        """``frame``: the frame on show with its ground truth read again (scene_gt.json was written), or None."""
        if frame is not None:
            self.frame = frame
            self.labels.publish_truth()

    def put_on_show(self, held: HeldRun | None) -> None:
        """Put a processed frame's ``held`` run (from the sequence's Next or a jump; None: the frame on show stays)
        in place of the engine's, and tell the server."""
        if held is None:
            return
        self.running, self.unshown = False, None
        self.frame, self.problem, self.estimator = held.frame, held.problem, held.estimator
        held.estimator.evaluator = self.evaluators.evaluating(held.problem)
        self.display.forget()
        self.results.put(p.Loaded(held.source, held.view, keep_camera=True))
        self.labels.adopt_frame(self.sequence.dataset)
        self.sequence_labels.show_on_frame()  # the sequence's labels, where they are started, over the saved ones
        self.sequence.publish(reports=[r.as_dict() for r in held.estimator.history])
        self.send_state("shown")
        self.publish()

    def load_session(self, cmd: p.LoadSession) -> None:
        """Continue a saved session. Everything that can fail on bad input happens before the current run is
        touched (``prepare_session``); stepping the restored estimator then continues the saved run bit for bit,
        given the same worker count (the tile a hypothesis is rendered in changes the last bits of its depth)."""
        from workbench.sessions import store as sessions

        prepared = prepare_session(cmd)
        if isinstance(prepared, p.SessionQuestion):
            self.results.put(prepared)
            return
        opened, source, view = prepared
        state, problem, config = opened.state, opened.problem, opened.config
        self.replace_frame(source, view, opened.frame, problem, config)  # from here on the current run is replaced
        try:
            self.estimator = sessions.restore_estimator(state, problem, self.evaluators.evaluator())
        except Exception:
            self.new_estimator()  # a fresh run on the session's frame: the server shows that frame already
            self.labels.adopt_frame(opened.dataset)
            self.sequence.start(source, opened.dataset, state.frame.split, view)
            self.sequence_labels.forget()
            raise
        est = self.estimator
        self.labels.adopt_frame(opened.dataset, labels=state.labels)
        self.results.put(p.SessionRestored(opened.name, opened.path, config, problem.config.likelihood.model,
                                           [r.as_dict() for r in est.history], opened.warnings))
        self.sequence.start(source, opened.dataset, state.frame.split, view, opened.sequence)
        self.sequence_labels.restore(None if opened.sequence is None else opened.sequence.labels)
        self.send_state("restored")
        if est.iteration >= 0:
            self.publish()

    def save_session(self, cmd: p.SaveSession) -> None:
        record = self.record()
        self.results.put(save_session(cmd, self.estimator, self.labels, self.evaluators.describe(), record))
        if record is not None:  # in a sequence, the session holds its labels
            self.sequence_labels.unsaved = False

    def record(self):
        """The sequence position a session saves, with the sequence labels on hand (None outside a sequence)."""
        record = self.sequence.record()
        return None if record is None else replace(record, labels=self.sequence_labels.labels)

    def close(self) -> None:
        self.sequence_labels.close()
        self.evaluators.close()
