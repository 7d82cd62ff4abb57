"""The estimator process: owns the problem, the worker pool and the ``Estimator``, and answers commands.

It runs in a ``spawn``ed process (forking after an OpenGL context exists hangs the child) so that the browser
server never waits for an iteration: the server puts commands on a queue and reads messages from a pipe (see
``engine_process``). Commands are drained between iterations, so a Pause takes effect after the iteration in
progress. A run starts an iteration only once the server has shown the last one (``protocol.Shown``): a slow
display holds the run back instead of falling behind it, and a Pause stops the run one iteration after the one on
display at the latest.

Labels and sessions are handled here too, because they need the estimator and a renderer: the server only shows
them. Label edits arrive as ``SetLabels`` on every gizmo move; the engine keeps the latest and renders its heatmap
once the command queue is empty, so a fast drag costs one render per pass, not one per mouse event.

A dead evaluation worker surfaces as ``WorkerCrashed`` (or a broken pipe): the pool is rebuilt and the iteration
retried once, and the user is told. If this whole process dies, ``engine_process.EngineClient`` (the server side)
restarts it and reloads the frame.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
import traceback
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from workbench.app import protocol as p
from workbench.errors import InputError
from workbench.inference.moves import MoveKind

log = logging.getLogger(__name__)

DEMO_DIR = Path(__file__).resolve().parents[2] / "assets" / "demo"
# Particles per snapshot; the rest are the least likely and add haze. Their wireframes were about half of every
# software-rendered frame's cost at 64.
DEFAULT_DISPLAY = 32
CRASH_ERRORS = (EOFError, BrokenPipeError, ConnectionError)


# ---------------------------------------------------------------------------------------------------------------
# Loading


def user_data_dir() -> Path:
    """Where the workbench keeps what a user may change: ``$WORKBENCH_HOME``, else ``$XDG_DATA_HOME/workbench``,
    else ``~/.local/share/workbench``."""
    if os.environ.get("WORKBENCH_HOME"):
        return Path(os.environ["WORKBENCH_HOME"]).expanduser()
    base = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(base).expanduser() / "workbench"


def demo_dataset() -> Path:
    """The demo the app shows, and saves labels into: ``user_data_dir()/demo``, copied once from the bundled
    ``assets/demo`` (or written by ``synth.make_demo`` when the checkout has none), so that nothing is ever saved
    into the installed package. An existing copy is used as it is: it may hold the user's labels."""
    out = user_data_dir() / "demo"
    if (out / "models" / "models_info.json").is_file():
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


def load(source: p.Source, likelihood: str):
    """-> (dataset folder, frame, problem) for ``source``; raises ``InputError`` naming the file at fault."""
    from workbench import bop
    from workbench.likelihood import LikelihoodConfig
    from workbench.pipeline import load_bop_problem
    from workbench.problem import ProblemConfig

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
    config = ProblemConfig(likelihood=LikelihoodConfig(model=likelihood))
    frame, problem = load_bop_problem(dataset, scene_id, im_id, config=config)
    return dataset, frame, problem


def title_of(source: p.Source, frame) -> str:
    name = "demo" if source.demo else Path(source.dataset).name
    return f"{name} · scene {frame.scene_id} · frame {frame.im_id}"


def expected_distinct(weights: np.ndarray, n: int) -> float:
    """How many distinct particles systematic resampling of ``weights`` (N,) (normalised) into ``n`` keeps, on
    average. Particle i's share n * w_i of the n evenly spaced pointers holds at least one of them with
    probability min(1, n * w_i) (one uniform offset for all), so the expectation is the sum of those."""
    return float(np.minimum(1.0, n * np.asarray(weights, dtype=np.float64)).sum())


# ---------------------------------------------------------------------------------------------------------------
# The engine


class Engine:
    def __init__(self, results, workers: int, ray=None):
        # results: what the engine tells the server, anything with a put (engine_process.Outbox, a test's list)
        self.results = results
        self.workers = workers
        self.ray = ray  # a distributed.RayConfig: evaluate on Ray actors; None: here or on local processes
        self.problem = None
        self.frame = None
        self.estimator = None
        self.evaluator = None
        self.explainer = None  # a LocalEvaluator in this process, for one particle's per-pixel likelihood
        self.config = None
        self.running = False
        self.unshown: int | None = None  # the iteration last published and not yet Shown by the server
        self.stop_on_convergence = True
        self.max_display = DEFAULT_DISPLAY
        self.order = np.zeros(0, int)  # particle indices of the last snapshot, most likely first
        self.rank = 0
        # Labels and sessions: the frame's place in its dataset (None: sessions unavailable, see frame_ref_problem)
        self.frame_ref = None
        self.frame_ref_problem = "nothing is loaded"
        self.labels: list[np.ndarray | None] = []
        self.label_heatmap = False
        self.label_dirty = False  # labels changed: heatmap and errors to recompute once the queue is drained
        # The log-likelihood of the known scene the Plots tab compares the estimate with: (kind, value) or None
        # while not yet computed; dropped whenever the labels, the frame or the likelihood change.
        self.reference: tuple[str | None, float] | None = None

    # -- commands

    def handle(self, cmd) -> None:
        if isinstance(cmd, p.Load):
            self.load(cmd)
        elif isinstance(cmd, p.Reset):
            self.reset(cmd.config, cmd.likelihood)
        elif isinstance(cmd, p.SetConfig):
            self.set_config(cmd.config)
        elif isinstance(cmd, p.Select):
            self.rank = max(0, int(cmd.rank))
            self.publish_chosen()
        elif isinstance(cmd, p.SetDisplay):
            self.max_display = max(1, int(cmd.max_particles))
            if self.estimator is not None and self.estimator.loglik is not None:
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
            if self.running:
                self.running = False
                self.send_state("paused")
        elif isinstance(cmd, p.SetLabels):
            self.set_labels(cmd)
        elif isinstance(cmd, p.SnapLabels):
            self.aside("labels", self.snap_labels)
        elif isinstance(cmd, p.FitLabels):
            self.aside("labels", self.fit_labels)
        elif isinstance(cmd, p.UseBestAsLabel):
            self.aside("labels", self.use_best_as_label)
        elif isinstance(cmd, p.SaveLabels):
            self.aside("labels", lambda: self.save_labels(cmd.overwrite_original))
        elif isinstance(cmd, p.SaveSession):
            self.aside("session", lambda: self.save_session(cmd))
        elif isinstance(cmd, p.LoadSession):
            self.aside("session", lambda: self.load_session(cmd))

    def aside(self, topic: str, action: Callable[[], None]) -> None:
        """A labelling or session action: bad input is reported next to its button and the run goes on (``fail``
        would stop it)."""
        try:
            action()
        except InputError as err:
            self.results.put(p.Failure(f"{topic.capitalize()}: not done", err.problem, err.path, topic=topic))

    def load(self, cmd: p.Load) -> None:
        cmd.config.validate()
        dataset, frame, problem = load(cmd.source, cmd.likelihood)  # on failure the old run stays
        from workbench.app.observation import build_view

        view = build_view(frame, problem, title_of(cmd.source, frame))
        self.close_evaluators()
        self.frame, self.problem, self.config = frame, problem, cmd.config
        self.results.put(p.Loaded(cmd.source, view))
        self.new_estimator()
        self.adopt_frame(dataset)

    def reset(self, config, likelihood: str) -> None:
        if self.problem is None:
            raise InputError(None, "nothing is loaded: load a dataset or the demo first")
        config.validate()
        self.config = config
        if likelihood != self.problem.config.likelihood.model:
            likelihood_config = replace(self.problem.config.likelihood, model=likelihood)
            likelihood_config.validate()
            self.problem = replace(self.problem, config=replace(self.problem.config, likelihood=likelihood_config))
            self.close_evaluators()  # the workers hold the old problem
        self.new_estimator()

    def set_config(self, config) -> None:
        config.validate()
        self.config = config
        if self.estimator is not None:
            self.estimator.set_config(config)

    def new_estimator(self) -> None:
        from workbench.estimators import Estimator

        self.running = False
        self.unshown = None  # a snapshot of the old run still on its way does not hold up the new one
        if self.evaluator is None:
            self.evaluator = self.make_evaluator()
        self.estimator = Estimator(self.problem, self.config, self.evaluator)
        self.order = np.zeros(0, int)
        self.reference = None
        self.send_state("reset")

    def make_evaluator(self, crash: BaseException | None = None):
        from workbench.evaluation import make_evaluator

        evaluator = make_evaluator(self.problem, self.workers, self.ray)
        # The pids serve the status line and the crash tests; a LocalEvaluator has none.
        pids = getattr(evaluator, "pids", [])
        reason = "" if crash is None else f"{type(crash).__name__}: {crash}"
        self.results.put(p.Workers(pids, crash is not None, reason))
        return evaluator

    def close_evaluators(self) -> None:
        for ev in {id(e): e for e in (self.evaluator, self.explainer) if e is not None}.values():
            try:
                ev.close()
            except Exception:  # a crashed pool may fail to close cleanly; it is being replaced anyway
                log.exception("closing an evaluator")
        self.evaluator = self.explainer = None

    def restart_workers(self, err: BaseException) -> None:
        log.warning("an evaluation worker died (%s: %s); starting a fresh pool and retrying the iteration",
                    type(err).__name__, err)
        try:
            self.evaluator.close()
        except Exception:
            log.exception("closing a crashed pool")
        if self.explainer is self.evaluator:
            self.explainer = None
        self.evaluator = self.make_evaluator(crash=err)
        self.estimator.evaluator = self.evaluator

    # -- running

    def start(self, stop_on_convergence: bool) -> None:
        if self.estimator is None:
            raise InputError(None, "nothing is loaded: load a dataset or the demo first")
        self.stop_on_convergence = stop_on_convergence
        if self.finished():
            self.results.put(p.Failure(
                "Nothing to run",
                f"the run is at iteration {self.estimator.iteration} of {self.config.iterations}"
                + (" and has converged" if self.estimator.converged else "")
                + ": raise the iteration budget, press Step, or Reset",
            ))
            return
        self.running = True
        self.send_state("running")

    def may_step(self) -> bool:
        """Running, and the server shows the last iteration (see ``protocol.Shown``)."""
        return self.running and self.unshown is None

    def finished(self) -> bool:
        est = self.estimator
        return est.iteration >= self.config.iterations or (
            self.stop_on_convergence and est.iteration >= 0 and est.converged
        )

    def step(self) -> None:
        from workbench.evaluation import WorkerCrashed

        if self.estimator is None:
            raise InputError(None, "nothing is loaded: load a dataset or the demo first")
        try:
            report = self.estimator.step()
        except (WorkerCrashed, *CRASH_ERRORS) as err:
            self.restart_workers(err)
            report = self.estimator.step()  # a second crash in a row is a Failure for the user
        if self.running and self.finished():
            self.running = False
        self.publish(report)
        if not self.running:
            self.send_state("converged" if report.converged else "done" if self.finished() else "paused")

    def publish(self, report=None) -> None:
        est = self.estimator
        if report is None:
            if not est.history:
                return
            report = est.history[-1]
        order = np.argsort(-est.loglik, kind="stable")  # -inf (failed physics, or outside the object region) last
        self.order = order
        top = order[: self.max_display]
        weights = est.weights()
        cloud = p.ParticleCloud(
            iteration=est.iteration,
            n_total=len(order),
            poses=est.projected[top].astype(np.float32),
            weights=weights[top],
            loglik=est.loglik[top],
            status=est.status[top],
        )
        row = report.as_dict()
        row["distinct_after_resampling"] = expected_distinct(weights, self.config.particles)
        row["reference"], row["reference_loglik"] = self.reference_loglik()
        self.results.put(p.Snapshot(row, cloud, self.running, self.config.particles))
        self.unshown = est.iteration
        self.publish_chosen()
        self.publish_label_errors()

    def reference_loglik(self) -> tuple[str | None, float]:
        """("label" or "truth", the log-likelihood of that scene as given) for the Plots tab, or (None, nan):
        the labels when every object is labelled, else the frame's ground truth when it has one for every object.
        One render, cached until the labels, frame or likelihood change."""
        if self.reference is None:
            kind, scene = None, None
            if self.labels and all(T is not None for T in self.labels):
                kind, scene = "label", np.stack(self.labels)
            elif self.frame is not None and self.frame.gt_T_cam_obj is not None:
                from workbench.geometry import invert_pose

                gt = invert_pose(self.problem.camera.T_cam_world)[None] @ self.frame.gt_T_cam_obj
                if len(gt) == self.problem.n_objects and np.all(np.isfinite(gt)):
                    kind, scene = "truth", gt
            value = float("nan")
            if scene is not None:
                pixels, _ = self.explain(scene)
                value = float(pixels.sum(dtype=np.float64))
            self.reference = (kind, value)
        return self.reference

    def publish_chosen(self) -> None:
        if self.estimator is None or len(self.order) == 0:
            return
        est = self.estimator
        rank = min(self.rank, len(self.order) - 1)
        i = int(self.order[rank])
        after = est.projected[i]
        pixels, residual = self.explain(after)
        self.results.put(p.Chosen(
            iteration=est.iteration,
            rank=rank,
            index=i,
            loglik=float(est.loglik[i]),
            weight=float(est.weights()[i]),
            status=int(est.status[i]),
            move=MoveKind(int(est.kinds[i])).label,
            before=est.hypotheses[i].copy(),
            after=after.copy(),
            pixel_loglik=pixels.astype(np.float32),
            residual=residual,
        ))

    def local_evaluator(self):
        """A LocalEvaluator of this process (the evaluator itself when it is one) for display and labelling."""
        from workbench.evaluation import LocalEvaluator

        if self.explainer is None:
            self.explainer = self.evaluator if isinstance(self.evaluator, LocalEvaluator) else LocalEvaluator(self.problem)
        return self.explainer

    def explain(self, scene: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One scene (K, 4, 4) as given -> (per-pixel log-likelihood, observed - predicted depth (NaN: either
        missing)) on the problem grid, from one render."""
        from workbench.likelihood import predicted_depth

        rendered, pixels = self.local_evaluator().explain(scene)
        predicted = predicted_depth(rendered[None], self.problem.background)[0]
        observed = self.problem.observed
        residual = np.where((observed > 0) & (predicted > 0), observed - predicted, np.nan).astype(np.float32)
        return pixels, residual

    def send_state(self, reason: str) -> None:
        it = -1 if self.estimator is None else self.estimator.iteration
        self.results.put(p.RunState(self.running, it, reason))

    def fail(self, err: BaseException) -> None:
        """Tell the user; stop running; keep serving."""
        self.running = False
        if isinstance(err, InputError):
            self.results.put(p.Failure("Input error", err.problem, err.path))
        else:
            log.error("engine error\n%s", traceback.format_exc())
            self.results.put(p.Failure(f"Estimator error ({type(err).__name__})", str(err) or repr(err)))
        self.send_state("error")

    # -- labels

    def adopt_frame(self, dataset: Path, labels: list | None = None) -> None:
        """Note where the loaded frame lives in its dataset (sessions and label files need it) and take its labels:
        ``labels`` (a session's), else those saved beside the dataset's ground truth, if any."""
        from workbench import labels as labelling
        from workbench import sessions

        frame, problem = self.frame, self.problem
        try:
            self.frame_ref, self.frame_ref_problem = sessions.frame_ref_for(dataset, frame, problem), ""
        except (InputError, OSError) as err:
            self.frame_ref, self.frame_ref_problem = None, str(err)
        note, reason = "", "session" if labels is not None else "frame"
        if labels is None:
            labels = [None] * problem.n_objects
            if self.frame_ref is not None:
                ref = self.frame_ref
                try:
                    labels = labelling.load_labels(Path(ref.dataset), frame.scene_id, frame.im_id,
                                                   problem.camera.T_cam_world, list(frame.object_ids), split=ref.split)
                except InputError as err:
                    self.results.put(p.Failure("Labels: not read", err.problem, err.path, topic="labels"))
                n = sum(T is not None for T in labels)
                if n:
                    where = labelling.labels_path(Path(ref.dataset), frame.scene_id, ref.split)
                    note = f"{n} label(s) read from `{where}`"
        self.labels = [None if T is None else np.array(T, dtype=np.float64) for T in labels]
        self.reference = None
        self.results.put(p.Labels(list(self.labels), reason, note))
        self.label_dirty = True

    def set_labels(self, cmd: p.SetLabels) -> None:
        if self.problem is None or len(cmd.labels) != self.problem.n_objects:
            return  # edits of a frame that has since been replaced
        self.labels = [None if T is None else np.array(T, dtype=np.float64) for T in cmd.labels]
        self.reference = None
        self.label_heatmap = cmd.heatmap
        self.label_dirty = True

    def labelled(self) -> list[int]:
        """The labelled objects; InputError when there are none."""
        which = [k for k, T in enumerate(self.labels) if T is not None]
        if self.problem is None or not which:
            raise InputError("labels", "nothing is labelled yet: move an object's gizmo, type its pose, or use the "
                                       "best estimate as label")
        return which

    def label_scene(self, leave_out: bool) -> tuple[np.ndarray, str]:
        """The labels as a whole scene (K, 4, 4) -> (scene, how unlabelled objects were filled in). Physics and the
        likelihood need every object somewhere: unlabelled ones take the best estimate; before the first
        iteration, with ``leave_out``, they are put behind the camera, out of the rendered view, else InputError."""
        from workbench.geometry import invert_pose

        missing = [k for k, T in enumerate(self.labels) if T is None]
        if not missing:
            return np.stack(self.labels), ""
        est = self.estimator
        if est is not None and est.projected is not None:
            fill, how = est.best, "best estimate"
        elif leave_out:
            behind = invert_pose(self.problem.camera.T_cam_world)
            behind[:3, 3] -= 100.0 * behind[:3, 2]  # 100 m behind the sensor: clipped, never drawn
            fill, how = np.broadcast_to(behind, (len(self.labels), 4, 4)), "left out"
        else:
            raise InputError("labels", "label every object, or take one estimator step so that its best estimate "
                                       "can stand in for the unlabelled ones")
        return np.stack([fill[k] if T is None else T for k, T in enumerate(self.labels)]).astype(np.float64), how

    def adopt_labels(self, scene: np.ndarray, which: list[int], reason: str, note: str) -> None:
        for k in which:
            self.labels[k] = np.array(scene[k], dtype=np.float64)
        self.reference = None
        self.results.put(p.Labels(list(self.labels), reason, note))
        self.label_dirty = True

    def object_name(self, k: int) -> str:
        from workbench.app.observation import display_names

        return display_names(self.problem.models)[k]

    def snap_labels(self) -> None:
        from workbench import labels as labelling
        from workbench.physics import STATUS_NAMES

        which = self.labelled()
        scene, filled = self.label_scene(leave_out=False)
        projected, moved, status = labelling.snap_to_plausible(self.problem, scene, self.local_evaluator())
        stand_in = f" (unlabelled objects: the {filled})" if filled else ""
        note = (f"**Snapped**: physics {STATUS_NAMES.get(status, status)}{stand_in}\n\n"
                + self.movement_table(which, moved, self.turned(scene, projected)))
        self.adopt_labels(projected, which, "snap", note)

    def fit_labels(self) -> None:
        from workbench import labels as labelling

        which = self.labelled()
        scene, filled = self.label_scene(leave_out=False)
        fitted = labelling.fit_label(self.problem, scene, self.local_evaluator())
        moved = np.linalg.norm(fitted[:, :3, 3] - scene[:, :3, 3], axis=-1)
        stand_in = f" (unlabelled objects: the {filled}, not changed)" if filled else ""
        note = (f"**Fitted** to the depth, then snapped{stand_in}\n\n"
                + self.movement_table(which, moved, self.turned(scene, fitted)))
        self.adopt_labels(fitted, which, "fit", note)

    def movement_table(self, which, moved: np.ndarray, turned: np.ndarray) -> str:
        """Markdown table of how far each labelled object moved (m -> cm) and turned (deg)."""
        rows = "\n".join(f"| {self.object_name(k)} | {moved[k] * 100:.2f} | {turned[k]:.1f} |" for k in which)
        return f"| object | moved (cm) | turned (°) |\n|---|---:|---:|\n{rows}"

    @staticmethod
    def turned(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        from workbench.geometry import rotation_angle

        return np.degrees(rotation_angle(np.swapaxes(a[:, :3, :3], -1, -2) @ b[:, :3, :3]))

    def use_best_as_label(self) -> None:
        est = self.estimator
        if est is None or est.projected is None:
            raise InputError("labels", "there is no estimate yet: take a step first")
        # Settled (Estimator.settle), as `workbench estimate` writes it: the search's scene fitted to the depth.
        best = est.settle().copy()
        moved = np.linalg.norm(best[:, :3, 3] - est.best[:, :3, 3], axis=-1)
        note = f"Labels set to the most likely scene of iteration {est.iteration}"
        if moved.any():
            note += f", settled to the depth (objects moved up to {moved.max() * 1e3:.1f} mm)"
        if est.ties:
            # The turns the depth scores about as well: a labeller checks these against the image or another view.
            note += ("\n\nThe depth hardly decides between these and the labels (check them; **Turn** or **Lay on "
                     "face** sets one):\n" + "\n".join(f"- {t.describe(self.problem)}" for t in est.ties))
        self.adopt_labels(best, list(range(len(best))), "best", note)

    def save_labels(self, overwrite_original: bool) -> None:
        from workbench import labels as labelling

        self.labelled()
        ref, frame = self.frame_ref, self.frame
        if ref is None:
            raise InputError(None, f"labels are saved into the frame's BOP dataset, and {self.frame_ref_problem}")
        started = time.time()
        path = labelling.save_labels(Path(ref.dataset), frame.scene_id, frame.im_id, self.problem.camera.T_cam_world,
                                     self.labels, list(frame.object_ids), overwrite_original=overwrite_original,
                                     split=ref.split)
        note = ""
        if overwrite_original:
            backups = [b for b in path.parent.glob(f"{path.name}.bak-*") if b.stat().st_mtime >= started - 1]
            note = f"the original was kept as `{max(backups).name}`" if backups else "there was no original to keep"
        self.results.put(p.Saved("labels", str(path), note))

    def publish_label_errors(self, always: bool = False) -> None:
        """The best scene against the labels (every iteration while something is labelled; ``always`` after an
        edit, so that clearing the labels clears the table)."""
        from workbench import labels as labelling

        est = self.estimator
        if est is None or est.projected is None or not (always or any(T is not None for T in self.labels)):
            return
        if len(self.labels) != self.problem.n_objects:
            return
        errors = labelling.label_errors(self.problem, est.best, self.labels)
        self.results.put(p.LabelErrors(est.iteration, errors))

    def label_work(self) -> None:
        """What the latest label edit needs: the errors, and the heatmap if it is shown. Runs once the command
        queue is drained, so edits that arrived meanwhile were simply overwritten (dropped, not rendered)."""
        self.label_dirty = False
        if self.problem is None:
            return
        try:
            self.publish_label_errors(always=True)
            if self.label_heatmap and any(T is not None for T in self.labels):
                scene, filled = self.label_scene(leave_out=True)
                pixels, residual = self.explain(scene)
                self.results.put(p.LabelHeatmap(pixels.astype(np.float32), residual,
                                                float(pixels.sum(dtype=np.float64)), filled))
        except InputError as err:
            self.results.put(p.Failure("Labels", err.problem, err.path, topic="labels"))
        except CRASH_ERRORS:
            raise
        except Exception as err:  # noqa: BLE001 - a display computation must not stop the run
            log.error("label heatmap\n%s", traceback.format_exc())
            self.results.put(p.Failure(f"Label heatmap failed ({type(err).__name__})", str(err), topic="labels"))

    # -- sessions

    def save_session(self, cmd: p.SaveSession) -> None:
        from workbench import sessions

        est = self.estimator
        if est is None:
            raise InputError(None, "nothing is loaded: load a dataset or the demo first")
        if self.frame_ref is None:
            raise InputError(None, f"this frame cannot be saved as a session: {self.frame_ref_problem}")
        state = sessions.session_state_from(est, self.frame_ref, self.labels)
        path = sessions.save_session(Path(cmd.directory), cmd.name, state, overwrite=cmd.overwrite)
        n = sum(T is not None for T in self.labels)
        self.results.put(p.Saved("session", str(path), f"iteration {est.iteration}, {n} of {len(self.labels)} "
                                                       f"objects labelled, {self.workers_used()} evaluation"))

    def workers_used(self) -> str:
        if self.ray is not None:
            return f"{self.workers} Ray actors"
        return "in-process" if self.workers <= 1 else f"{self.workers} workers"

    def load_session(self, cmd: p.LoadSession) -> None:
        """Continue a saved session. Everything that can fail on bad input happens before the current run is
        touched; stepping the restored estimator then continues the saved run bit for bit, given the same worker
        count (the tile a hypothesis is rendered in changes the last bits of its depth)."""
        from workbench import sessions
        from workbench.app.observation import build_view

        path = Path(cmd.path)
        state = sessions.load_session(path)
        warnings = sessions.check_dataset(state)
        frame = problem = None
        if not warnings:
            frame, problem = sessions.session_problem(state)
            warnings = sessions.check_dataset(state, problem)
        if warnings and not cmd.confirmed:
            self.results.put(p.SessionQuestion(path, warnings))
            return
        if problem is None:
            frame, problem = sessions.session_problem(state)
        dataset = Path(state.frame.dataset)
        if dataset.resolve() in (DEMO_DIR, user_data_dir().resolve() / "demo"):
            source = p.Source(demo=True)
        else:
            split = dataset / state.frame.split if state.frame.split else dataset
            source = p.Source(split, frame.scene_id, frame.im_id)
        name = path.name.removesuffix(".json")
        view = build_view(frame, problem, f"session {name} · {dataset.name} · scene {frame.scene_id} · "
                                         f"frame {frame.im_id}")

        # From here on the current run is replaced.
        self.running = False
        self.close_evaluators()
        self.frame, self.problem, self.config = frame, problem, state.estimator_config
        self.order = np.zeros(0, int)
        self.results.put(p.Loaded(source, view))
        try:
            self.evaluator = self.make_evaluator()
            self.estimator = sessions.restore_estimator(state, problem, self.evaluator)
        except Exception:
            self.new_estimator()  # a fresh run on the session's frame: the server shows that frame already
            self.adopt_frame(dataset)
            raise
        est = self.estimator
        self.adopt_frame(dataset, labels=state.labels)
        self.results.put(p.SessionRestored(name, path, state.estimator_config, problem.config.likelihood.model,
                                           [r.as_dict() for r in est.history], warnings))
        self.send_state("restored")
        if est.iteration >= 0:
            self.publish()

    def close(self) -> None:
        self.close_evaluators()
