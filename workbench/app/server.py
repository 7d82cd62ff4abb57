"""The browser workbench: a viser server showing one estimation run, driven from its control panel.

    workbench serve [DATASET --scene ID --frame ID | --demo | --session PATH] [--sessions-dir DIR]
                    [--host 127.0.0.1] [--port 8080]

The estimator lives in a separate process (``engine.py``); this process only draws. GUI and scene are viser's
server-wide ones, so every open tab sees and drives the same run. Messages from the engine arrive on a reader
thread and GUI callbacks on viser's threads: ``App`` serialises both with one lock.
"""

from __future__ import annotations

import errno
import logging
import socket
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import viser

from workbench.app import protocol as p
from workbench.app.camera import FRAME_OBJECTS, CameraPose, apply_camera, frame_objects, from_sensor
from workbench.app.colors import VIRIDIS, legend_html, view_legend_html
from workbench.app.engine import DEMO_DIR
from workbench.app.engine_process import EngineClient
from workbench.app.labelling import Labelling
from workbench.app.panel import Panel, build_panel
from workbench.app.quiet import Quiet
from workbench.app.scene_throttle import SceneThrottle
from workbench.app.sessions_panel import Sessions
from workbench.app.views import ChosenLayer, HeatmapLayer, ObservationLayer, ParticleLayer, light_cheaply
from workbench.errors import InputError
from workbench.estimators import EstimatorConfig
from workbench.geometry import rotation_angle
from workbench.physics import STATUS_NAMES

log = logging.getLogger(__name__)

# Small enough for one software-rendered machine to iterate at a few Hz; the panel changes it.
DEFAULT_CONFIG = EstimatorConfig(particles=128, iterations=60)
SESSIONS_DIR = Path("sessions")
CAMERA_REST_S = 0.5  # a tab's camera is remembered (for reloads and new tabs) once it rested this long
# While the estimator runs, the 3D view is redrawn at most once per this many seconds. Every batch of scene messages
# makes viser's client draw frames for 250 ms, and a software-rendered frame costs ~0.2 s of CPU, so each redraw
# costs ~0.5 s of CPU: a redraw per iteration (and Chosen apart from Snapshot) kept Chromium busy. The panel's text
# and plots still follow every iteration.
SCENE_INTERVAL_S = 1.0
SCENE_GATHER_S = 0.1  # a deferred redraw waits this long at least, for the rest of its iteration (Chosen)


@dataclass
class RunView:
    """What the server knows about the run, for the status line and the tests."""

    iteration: int = -1
    running: bool = False
    reports: list[dict] = field(default_factory=list)
    cloud: p.ParticleCloud | None = None
    chosen: p.Chosen | None = None
    view: p.ObservationView | None = None
    last_state: p.RunState | None = None
    failures: list[p.Failure] = field(default_factory=list)
    worker_pids: list[int] = field(default_factory=list)
    engine_pid: int | None = None
    restarts: int = 0
    pause_requested_at: int | None = None  # the iteration on display when Pause was pressed
    display_errors: list[str] = field(default_factory=list)  # bugs in drawing a message (logged, kept for tests)


class App:
    def __init__(self, server: viser.ViserServer, source: p.Source | None, workers: int,
                 config: EstimatorConfig = DEFAULT_CONFIG, likelihood: str = "robust",
                 sessions_dir: Path = SESSIONS_DIR, session: Path | None = None, ray=None):
        self.server = server
        self.lock = threading.RLock()
        self.quiet = Quiet()  # set while the server itself writes controls: their callbacks must not echo
        self.config = config
        self.source: p.Source | None = None  # the last frame the engine loaded
        self.state = RunView()
        self.names: list[str] = []  # the loaded objects' display names, as every part of the panel shows them
        self.camera_pose: CameraPose | None = None  # where new and reloaded tabs start
        self._camera_moved: CameraPose | None = None
        self._camera_timer: threading.Timer | None = None
        self.changed = threading.Condition(self.lock)  # notified on every engine message (tests wait on it)
        self.scene_throttle = SceneThrottle(server, self.lock, SCENE_INTERVAL_S, SCENE_GATHER_S,
                                            self.drawing_failed)
        self.panel: Panel = build_panel(server.gui, config, likelihood)
        light_cheaply(server)
        self.observation = ObservationLayer(server)
        self.particles = ParticleLayer(server, on_pick=self.pick)
        self.chosen = ChosenLayer(server)
        self.heatmap = HeatmapLayer(server)
        self.labelling = Labelling(server, self.panel.label, self.send, self.lock, self.quiet,
                                   on_heatmap_mode=self.label_heatmap_mode_changed)
        self.sessions = Sessions(self.panel.sessions, sessions_dir, self.send, self.lock, self.quiet)
        self._wire()
        self.engine = EngineClient(workers, self.on_message, self.on_engine_died, ray=ray)
        if session is not None:
            # As the Sessions tab's Load: the engine asks first if the dataset changed; a bad file is a message.
            self.panel.title.content = f"**workbench** · loading session {session} …"
            self.sessions.load_path(session)
        elif source is not None:
            self.load(source)

    # -- commands from the panel

    def _wire(self) -> None:
        P = self.panel
        P.step.on_click(lambda _: self.send(p.Step()))
        P.run.on_click(lambda _: self.send(p.Run(P.stop_on_convergence.value)))
        P.pause.on_click(lambda _: self.pause())
        P.reset.on_click(lambda _: self.reset())
        for h in (P.method, P.particles, P.iterations, P.sigma_xy, P.sigma_z, P.sigma_angles):
            h.on_update(lambda _: self.config_changed())
        P.rank.on_update(lambda _: self.send(p.Select(int(P.rank.value))))
        P.best.on_click(lambda _: self.pick(0))
        P.scene_mode.on_update(lambda _: self.redraw_chosen())
        P.heatmap_mode.on_update(lambda _: self.heatmap_mode_changed())
        for h in (P.show_observation, P.show_gt):
            h.on_update(lambda _: self.observation.set_visible(P.show_observation.value, P.show_gt.value))
        for h in (P.show_particles, P.show_best):
            h.on_update(lambda _: self.particles.set_visible(P.show_particles.value, P.show_best.value))
        P.max_particles.on_update(lambda _: self.send(p.SetDisplay(int(P.max_particles.value))))
        P.load.on_click(lambda _: self.load_typed())
        P.camera.on_click(lambda event: self.camera_preset(event.target.value, event.client))
        self.server.on_client_connect(self.client_connected)
        P.demo.on_click(lambda _: self.load(p.Source(demo=True)))

    def send(self, cmd) -> None:
        self.engine.send(cmd)

    def guarded(self, action) -> None:
        """Run a panel action; bad input becomes a message in the panel, never a dead callback. An action that
        goes through clears the banner of an earlier bad input: the user corrected it."""
        try:
            action()
        except InputError as err:
            self.report(p.Failure("Input error", err.problem, err.path))
        else:
            self.clear_error()

    def clear_error(self) -> None:
        """Hide the error banner, unless the estimator is gone for good (only a restart helps then)."""
        with self.lock:
            last = self.state.failures[-1] if self.state.failures else None
            if self.panel.error.visible and not (last is not None and last.fatal):
                self.panel.error.visible = False

    def config_changed(self) -> None:
        if self.quiet.active:
            return  # a restored session's settings being shown, not a user's edit

        def apply():
            self.config = self.panel.estimator_config(self.config)
            self.send(p.SetConfig(self.config))

        self.guarded(apply)

    def pause(self) -> None:
        # Sent under the lock, so it reaches the engine before the Shown of any later iteration (on_snapshot sends
        # that under the lock too): the run stops at most one iteration after the one on display.
        with self.lock:
            self.state.pause_requested_at = self.state.iteration
            self.send(p.Pause())

    def reset(self) -> None:
        def apply():
            self.config = self.panel.estimator_config(self.config)
            self.send(p.Reset(self.config, self.panel.likelihood.value))

        self.guarded(apply)

    def load(self, source: p.Source) -> None:
        self.panel.title.content = f"**workbench** · loading {source.describe()} …"
        self.send(p.Load(source, self.config, self.panel.likelihood.value))

    def load_typed(self) -> None:
        def apply():
            text = self.panel.dataset.value.strip()
            if not text:
                raise InputError("Dataset", "type the path of a BOP dataset folder")
            scene_id, im_id = self.panel.frame_ids()
            self.load(p.Source(dataset=Path(text).expanduser(), scene_id=scene_id, im_id=im_id))

        self.guarded(apply)

    def pick(self, rank: int) -> None:
        """Choose the particle at ``rank``: moving the shared slider sends the Select (and shows every tab)."""
        rank = int(np.clip(rank, 0, self.panel.rank.max))
        if self.panel.rank.value == rank:
            self.send(p.Select(rank))
        else:
            self.panel.rank.value = rank

    # -- messages from the engine

    def on_message(self, msg) -> None:
        with self.lock:
            handler = {
                p.Ready: self.on_ready,
                p.Loaded: self.on_loaded,
                p.Snapshot: self.on_snapshot,
                p.Chosen: self.on_chosen,
                p.RunState: self.on_run_state,
                p.Failure: self.report,
                p.Workers: self.on_workers,
                p.Labels: self.labelling.show_labels,
                p.LabelHeatmap: self.labelling.show_heatmap,
                p.LabelErrors: self.labelling.show_errors,
                p.Saved: self.on_saved,
                p.SessionQuestion: self.sessions.on_question,
                p.SessionRestored: self.on_session_restored,
            }[type(msg)]
            try:
                handler(msg)
            except Exception as err:  # a drawing bug must not stop the messages that follow
                self.drawing_failed(type(msg).__name__, err)
            finally:
                self.changed.notify_all()

    def drawing_failed(self, what: str, err: Exception) -> None:
        """Log a bug in drawing ``what`` (a message type or a throttled drawing) and keep it for the tests."""
        log.error("drawing %s", what, exc_info=err)
        with self.lock:
            self.state.display_errors.append(f"{what}: {err!r}")

    def on_ready(self, msg: p.Ready) -> None:
        self.state.engine_pid = msg.pid

    def on_loaded(self, msg: p.Loaded) -> None:
        view, P = msg.view, self.panel
        self.source = msg.source  # what a restarted engine reloads
        old = self.state
        self.scene_throttle.cancel()
        self.state = replace(RunView(), view=view, engine_pid=old.engine_pid, restarts=old.restarts,
                             failures=old.failures, display_errors=old.display_errors)
        with self.server.atomic():
            P.title.content = f"**workbench** · {view.title}"
            P.error.visible = False
            self.observation.draw(view, P.show_observation.value, P.show_gt.value)
            self.particles.set_frame(view.meshes)
            self.chosen.set_frame(view)
            self.heatmap.set_frame(view)
            self.labelling.set_frame(view)
            self.sessions.on_frame(view.title)
            P.depth_image.image = view.depth_image
            P.depth_image.visible = True
            lo, hi = view.depth_range
            P.depth_legend.content = legend_html("depth (m)", f"{lo:.2f}", f"{hi:.2f}", VIRIDIS,
                                                 f"3D points: {view.color_legend}")
            P.heat_image.visible = False
            P.legend.content = ""
            P.physics_change.content = ""
            P.plots.clear()
            self.names = [m.name for m in view.meshes]
            self.show_view_legend()
        self.camera_preset(FRAME_OBJECTS, None)

    def show_view_legend(self) -> None:
        view = self.state.view
        if view is None:
            return
        heat = self.panel.heatmap_mode.value != "off" or self.panel.label.heatmap.value != "off"
        note = "observed points replaced by a heatmap: its colours are explained beside it" if heat else ""
        content = view_legend_html(self.names, view.color_legend, note)
        if self.panel.view_legend.content != content:
            self.panel.view_legend.content = content

    def camera_preset(self, which: str, client: viser.ClientHandle | None) -> None:
        """Point the camera at the objects (``FRAME_OBJECTS``) or put it where the depth sensor was; for one
        browser tab (``client``) or every tab and every later one."""
        view = self.state.view
        if view is None:
            return
        pose = frame_objects(view) if which == FRAME_OBJECTS else from_sensor(view)
        self.set_initial_camera(pose)
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            apply_camera(c.camera, pose)

    def set_initial_camera(self, pose: CameraPose) -> None:
        """Where a new or reloaded tab starts."""
        with self.lock:
            self.camera_pose = pose
        apply_camera(self.server.initial_camera, pose)

    def client_connected(self, client: viser.ClientHandle) -> None:
        """A new tab (or a reload) starts where the last camera was left, not back at the default view."""
        def moved(camera: viser.CameraHandle) -> None:
            with self.lock:
                self._camera_moved = CameraPose(tuple(camera.position), tuple(camera.look_at))
                due = self._camera_timer is None
                if due:  # remembered once the camera has rested a moment: a drag reports ~30 poses a second
                    self._camera_timer = threading.Timer(CAMERA_REST_S, self._remember_camera)
                    self._camera_timer.daemon = True
                    self._camera_timer.start()

        client.camera.on_update(moved)

    def _remember_camera(self) -> None:
        with self.lock:
            pose, self._camera_timer = self._camera_moved, None
        if pose is not None:
            self.set_initial_camera(pose)

    def on_snapshot(self, msg: p.Snapshot) -> None:
        s, P = self.state, self.panel
        if s.reports and s.reports[-1]["iteration"] == msg.report["iteration"]:
            s.reports.pop()  # a republished iteration (e.g. more particles drawn), not a new one
        s.reports.append(msg.report)
        s.cloud, s.iteration, s.running = msg.cloud, msg.report["iteration"], msg.running
        self.send(p.Shown(s.iteration))  # the engine may start the next iteration (see protocol.Shown)
        self.scene_throttle.submit("particles", lambda: self.draw_particles(msg.cloud), defer=msg.running)
        P.rank.max = max(1, msg.cloud.n_total - 1)
        self.clear_error()  # an iteration went through: whatever failed before was dealt with
        P.plots.add(msg.report, msg.cloud.n_total, self.config.converge_position, self.config.converge_degrees)
        P.timings.content = timings_markdown(msg.report)
        P.status.content = self.status_markdown()

    def draw_particles(self, cloud: p.ParticleCloud) -> None:
        """The particle cloud and the most likely scene (which an unlabelled selected object's gizmo follows)."""
        self.particles.update(cloud)
        if len(cloud.poses):
            self.labelling.show_estimate(cloud.poses[0])

    def on_chosen(self, msg: p.Chosen) -> None:
        self.state.chosen = msg
        self.scene_throttle.submit("chosen", self.redraw_chosen, defer=self.state.running)

    def redraw_chosen(self) -> None:
        with self.lock:
            c, P = self.state.chosen, self.panel
            self.chosen.update(c, P.scene_mode.value)
            legend, image = self.heatmap.update(c, P.heatmap_mode.value)
            P.legend.content = legend
            if image is not None:
                P.heat_image.image = image
            P.heat_image.visible = image is not None
            P.physics_change.content = physics_markdown(c, self.names) if c is not None else ""

    def heatmap_mode_changed(self) -> None:
        # The heatmap is drawn on the observed points: showing both would bury one under the other. So would the
        # label heatmap, on the same points: one heatmap at a time.
        if self.panel.heatmap_mode.value != "off" and self.panel.label.heatmap.value != "off":
            self.panel.label.heatmap.value = "off"
        self.panel.show_observation.value = self.panel.heatmap_mode.value == "off" and \
            self.panel.label.heatmap.value == "off"
        self.show_view_legend()
        self.redraw_chosen()

    def label_heatmap_mode_changed(self) -> None:
        if self.panel.label.heatmap.value != "off" and self.panel.heatmap_mode.value != "off":
            self.panel.heatmap_mode.value = "off"
        self.panel.show_observation.value = self.panel.heatmap_mode.value == "off" and \
            self.panel.label.heatmap.value == "off"
        self.show_view_legend()

    def on_run_state(self, msg: p.RunState) -> None:
        s, P = self.state, self.panel
        s.last_state, s.running = msg, msg.running
        if msg.reason == "reset":
            self.scene_throttle.cancel()
            s.reports, s.cloud, s.chosen, s.iteration = [], None, None, -1
            P.plots.clear()
            self.particles.set_frame(self.particles.meshes)
            self.redraw_chosen()
            self.labelling.show_estimate(None)
        elif not msg.running:
            self.scene_throttle.flush()  # the run stopped: show where it stopped now
        P.run.disabled = msg.running
        P.pause.disabled = not msg.running
        P.step.disabled = msg.running
        P.status.content = self.status_markdown()

    def on_workers(self, msg: p.Workers) -> None:
        self.state.worker_pids = msg.pids
        if msg.restarted:
            self.state.restarts += 1
            self.notify("Evaluation worker restarted", f"A worker process died ({msg.reason}); a fresh pool took "
                        "over and the iteration was retried. The run goes on.", color="yellow")
        where = f"{len(msg.pids)} worker processes" if msg.pids else "in the estimator process"
        restarts = f" · restarted {self.state.restarts}×" if self.state.restarts else ""
        self.panel.workers.content = f"Evaluation: {where}{restarts}"

    def on_engine_died(self, exitcode: int | None, gave_up: bool) -> None:
        with self.lock:
            self.state.restarts += 1
            source = self.source
        if gave_up:
            log.error("the estimator process died again (exit code %s) and was not restarted: restart the server",
                      exitcode)
        else:
            log.warning("the estimator process died (exit code %s); restarted it%s", exitcode,
                        " and reloading the frame" if source else "")
        if gave_up:
            self.report(p.Failure("Estimator process keeps dying", f"it exited with code {exitcode} again and was "
                                  "not restarted; see the server's log, then restart the server", fatal=True))
            return
        self.notify("Estimator process restarted",
                    f"The estimator process died (exit code {exitcode}); it was restarted"
                    + (" and the frame reloaded: the run starts again." if source else "."), color="yellow")
        if source is not None:
            self.send(p.Load(source, self.config, self.panel.likelihood.value))

    def on_saved(self, msg: p.Saved) -> None:
        if msg.kind == "session":
            self.sessions.on_saved(msg)
        else:
            self.labelling.show_saved(msg)
        # Also where it is seen: the tab's own message can be below the fold of a long panel.
        self.notify(f"Saved {msg.kind}", f"{msg.path}{' · ' + msg.note if msg.note else ''}", color="green")

    def on_session_restored(self, msg: p.SessionRestored) -> None:
        """Show the restored run's settings and history (its frame came in ``Loaded`` just before)."""
        s, P = self.state, self.panel
        self.config = msg.config
        with self.quiet:  # the engine has these settings already; showing them must not send them back
            P.show_config(msg.config, msg.likelihood)
        s.reports = list(msg.reports)
        s.iteration = msg.reports[-1]["iteration"] if msg.reports else -1
        P.plots.set_history(msg.reports, msg.config.particles, msg.config.converge_position,
                            msg.config.converge_degrees)
        self.sessions.on_restored(msg)
        P.status.content = self.status_markdown()

    def report(self, failure: p.Failure) -> None:
        # The terminal hears of every failure too: a server started on a bad path must not look healthy there.
        log.warning("%s: %s%s", failure.title, f"{failure.path}: " if failure.path else "", failure.problem)
        with self.lock:
            if failure.topic == "session":
                self.sessions.on_failure(failure)
            elif failure.topic == "labels":
                self.labelling.show_failure(failure)
            self.state.failures.append(failure)
            where = f"`{failure.path}`: " if failure.path else ""
            self.panel.error.content = f"**⚠ {failure.title}** — {where}{failure.problem}"
            self.panel.error.visible = True
            view = self.state.view  # a failed load leaves the loaded frame in place
            self.panel.title.content = f"**workbench** · {view.title if view else 'nothing loaded'}"
        self.notify(failure.title, f"{failure.path + ': ' if failure.path else ''}{failure.problem}", color="red")

    def notify(self, title: str, body: str, color: str) -> None:
        for client in self.server.get_clients().values():
            client.add_notification(title, body, color=color, auto_close_seconds=15.0)

    def status_markdown(self) -> str:
        s, cfg = self.state, self.config
        if not s.reports:
            state = "running" if s.running else "paused"
            return f"No iterations yet ({cfg.iterations} planned) · {state}. Press **Step** or **Run**."
        r = s.reports[-1]
        it = r["iteration"]
        if s.running:
            state = "running"
        elif r["converged"]:
            state = "**finished**: converged"
        elif it >= cfg.iterations:
            state = "**finished**: iteration budget reached"
        else:
            state = "paused"
        counter = f"Iteration {it} of {cfg.iterations}" if it <= cfg.iterations else \
            f"Iteration {it}, {it - cfg.iterations} past the budget of {cfg.iterations}"
        rule = f"< {cfg.converge_position * 100:g} cm and < {cfg.converge_degrees:g}°"
        if r["converged"]:
            conv = f"**converged**: the best scene moved {rule} for {cfg.converge_patience} iterations"
        else:
            calm = 0
            for row in reversed(s.reports):
                if row["best_move_m"] < cfg.converge_position and row["best_move_deg"] < cfg.converge_degrees:
                    calm += 1
                else:
                    break
            last = "" if not np.isfinite(r["best_move_m"]) else \
                f"; last it moved {r['best_move_m'] * 100:.1f} cm, {r['best_move_deg']:.1f}°"
            conv = f"calm {min(calm, cfg.converge_patience)} of {cfg.converge_patience} (calm: best moves {rule}{last})"
        accept = "" if np.isnan(r["accept_rate"]) else f" · accepted {r['accept_rate'] * 100:.0f} %"
        return (
            f"**{counter}** · {state}  \n{conv}  \n"
            f"best log-lik {r['best_loglik']:.1f} (from a {r.get('best_kind') or 'start'} move) · β {r['beta']:.3g}"
            f" · failed physics or outside the object region {r['n_failed']}{accept} · objects rest {r.get('sink_m', 0.0) * 1000:.0f} mm below"
            f" the fitted table"
        )

    # -- lifetime

    def stop(self) -> None:
        self.scene_throttle.cancel()
        self.engine.stop()

    def wait_for(self, predicate, timeout: float) -> bool:
        """Block until ``predicate(self.state)`` holds (checked on every engine message), or the timeout."""
        deadline = time.monotonic() + timeout
        with self.changed:
            while not predicate(self.state):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.changed.wait(min(left, 0.5))
        return True


def timings_markdown(report: dict) -> str:
    t = report["timings"]
    rows = "\n".join(f"| {stage} | {t.get(stage, 0.0) * 1000:.1f} |"
                     for stage in ("projection", "render", "likelihood", "resampling", "total"))
    return ("| stage | ms |\n|---|---:|\n" + rows +
            "\n\n<small>projection, render and likelihood are summed over the workers; total is wall time</small>")


def physics_markdown(c: p.Chosen, names: list[str]) -> str:
    """How far physics moved each object of the chosen particle (``names``: the objects' display names)."""
    moved = np.linalg.norm(c.after[:, :3, 3] - c.before[:, :3, 3], axis=-1)
    turned = np.degrees(rotation_angle(np.swapaxes(c.before[:, :3, :3], -1, -2) @ c.after[:, :3, :3]))
    rows = "\n".join(f"| {name} | {m * 100:.1f} | {a:.1f} |" for name, m, a in zip(names, moved, turned))
    return (
        f"Rank **{c.rank}** (particle {c.index}) · log-lik {c.loglik:.1f} · weight {c.weight:.3g} · "
        f"proposed by: {c.move} move · physics: {STATUS_NAMES.get(c.status, c.status)}\n\n"
        f"| object | moved (cm) | turned (°) |\n|---|---:|---:|\n{rows}"
    )


def port_in_use_message(host: str, port: int) -> str:
    return f"port {port} on {host} is in use (another workbench?): stop that program or pass another --port"


def check_port_free(host: str, port: int) -> None:
    """InputError unless ``host:port`` can be listened on (viser would quietly take the next free port, and the
    user's bookmark would reach whatever holds this one). Port 0 means any free port."""
    if port == 0:
        return
    try:
        addresses = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as e:
        raise InputError("--host", f"cannot resolve {host!r} ({e})") from e
    for family, kind, proto, _, address in addresses:
        with socket.socket(family, kind, proto) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: TIME_WAIT is free
            try:
                sock.bind(address)
            except OSError as e:
                if e.errno == errno.EADDRINUSE:
                    raise InputError("--port", port_in_use_message(host, port)) from e
                raise InputError("--host", f"cannot listen on {host}:{port} ({e.strerror})") from e


@dataclass
class AppHandle:
    """A running workbench; ``stop()`` ends the engine process and the web server."""

    server: viser.ViserServer
    app: App
    url: str

    def stop(self) -> None:
        self.app.stop()
        self.server.stop()


def serve(
    dataset: Path | None = None,
    scene_id: int | None = None,
    im_id: int | None = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    demo: bool = False,
    block: bool = True,
    workers: int = 2,
    config: EstimatorConfig = DEFAULT_CONFIG,
    likelihood: str = "robust",
    session: Path | None = None,
    sessions_dir: Path | None = None,
    ray=None,
) -> AppHandle:
    """Start the workbench on ``host:port`` (localhost unless told otherwise) with ``dataset``'s frame, or the demo
    (``demo``, or no dataset), or continuing the saved ``session`` (a session JSON file). Sessions are saved to and
    listed from ``sessions_dir`` (default: the session's folder, else ./sessions). ``block``: serve until Ctrl-C
    and then stop; else return the handle at once. ``ray`` (a distributed.RayConfig): evaluate each batch on
    ``workers`` Ray actors instead of local processes, with the same results.

    A session continues bit for bit only with the worker count it was saved with (``workers``; the command line
    uses 2), on either engine: the tile a hypothesis is rendered in changes the last bits of its depth."""
    # The CLI names the bundled demo folder, which a checkout may not hold yet: the engine writes it on demand.
    demo = demo or dataset is None or Path(dataset).resolve() == DEMO_DIR
    source = p.Source(demo=True) if demo else p.Source(Path(dataset), scene_id, im_id)
    if sessions_dir is None:
        sessions_dir = Path(session).parent if session is not None else SESSIONS_DIR
    check_port_free(host, port)
    server = viser.ViserServer(host=host, port=port, label="workbench")
    if port != 0 and server.get_port() != port:  # taken between the check and the bind: viser moved on
        server.stop()
        raise InputError("--port", port_in_use_message(host, port))
    app = App(server, None if session is not None else source, workers, config, likelihood, sessions_dir,
              None if session is None else Path(session), ray=ray)
    handle = AppHandle(server, app, f"http://{host}:{server.get_port()}")
    if not block:
        return handle
    what = f"session {session}" if session is not None else source.describe()
    print(f"workbench: serving {what} at {handle.url} (Ctrl-C stops)", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        handle.stop()
    return handle
