"""The browser workbench: a viser server showing one estimation run, driven from its control panel.

    workbench serve [DATASET --scene ID --frame ID | --demo | --session PATH] [--sessions-dir DIR]
                    [--host 127.0.0.1] [--port 8080]

The estimator lives in a separate process (``engine.py``); this process only draws. GUI and scene are viser's
server-wide ones, so every open tab sees and drives the same run. Messages from the engine arrive on a reader
thread and GUI callbacks on viser's threads: ``App`` serialises both with one lock.
"""

from __future__ import annotations

import errno
import socket
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import viser

from workbench.app import protocol as p
from workbench.app.ui.run.camera import FRAME_OBJECTS, TabCameras
from workbench.app.engine.engine import DEMO_DIR
from workbench.app.engine.process import EngineClient
from workbench.app.ui.labelling.labelling import Labelling
from workbench.app.ui.panel import Panel, build_panel, visibility_item
from workbench.app.engine.snapshot import default_drawn
from workbench.app.ui.widgets.quiet import Quiet
from workbench.app.ui.reporting import Reporter
from workbench.app.ui.run.display import RunDisplay
from workbench.app.ui.sequence.panel import SequencePanel
from workbench.app.ui.sessions.panel import Sessions
from workbench.app.ui.run.settings import SettingsForm
from workbench.app.ui.run.status import RunView, status_markdown, timings_markdown
from workbench.app.ui.run.step_button import StepButton
from workbench.app.ui.run.truth import truth_markdown
from workbench.errors import InputError
from workbench.inference.config import EstimatorConfig

# Small enough for one software-rendered machine to iterate at a few Hz; the panel changes it.
DEFAULT_CONFIG = EstimatorConfig(particles=128, iterations=60)
SESSIONS_DIR = Path("sessions")


class App:
    """One run shown in every browser tab: the panel's commands go to the engine process, its messages come back
    here. Drawing them is ``display``'s job, telling the user about failures and restarts ``reporter``'s."""

    def __init__(self, server: viser.ViserServer, source: p.Source | None, workers: int,
                 config: EstimatorConfig = DEFAULT_CONFIG, likelihood: str = "robust",
                 sessions_dir: Path = SESSIONS_DIR, session: Path | None = None, ray=None):
        self.server = server
        self.lock = threading.RLock()
        self.quiet = Quiet()  # set while the server itself writes controls: their callbacks must not echo
        self.source: p.Source | None = None  # the last frame the engine loaded
        self.state = RunView()
        self.drawn_by_user = False  # whether the user has set Particles drawn (else each frame gets its share)
        self.changed = threading.Condition(self.lock)  # notified on every engine message (tests wait on it)
        self.cameras = TabCameras(server, self.lock)
        self.panel: Panel = build_panel(server.gui, config, likelihood)
        self.labelling = Labelling(server, self.panel.label, self.send, self.lock, self.quiet,
                                   on_heatmap_mode=lambda: self.display.label_heatmap_mode_changed())
        self.sessions = Sessions(self.panel.sessions, sessions_dir, self.send, self.lock, self.quiet,
                                 iteration=lambda: self.state.iteration)
        self.reporter = Reporter(server, self.panel, self.lock, lambda: self.state, self.labelling, self.sessions)
        self.settings = SettingsForm(self.panel, self.lock, self.quiet, self.reporter, self.send, config, likelihood)
        self.stepper = StepButton(self.panel, self.lock, self.send, lambda: self.state.running, self.settings.revert)
        self.display = RunDisplay(server, self.panel, self.lock, self.labelling, on_pick=self.pick,
                                  on_error=self.reporter.drawing_failed)
        self.sequence = SequencePanel(self.panel.sequence, self.lock, self.send, self.reporter.topics,
                                      self.show_history, names=lambda: self.display.names)
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
        P, display = self.panel, self.display
        P.step.on_click(lambda _: self.stepper.press())
        P.run.on_click(lambda _: self.run())
        P.pause.on_click(lambda _: self.pause())
        P.reset.on_click(lambda _: self.reset())
        for h in (P.method, P.particles, P.iterations, P.sigma_xy, P.sigma_z, P.sigma_angles, P.seed):
            h.on_update(lambda _: self.settings.changed())
        P.likelihood.on_update(lambda _: self.settings.show_pending())
        P.rank.on_update(lambda _: self.send(p.Select(int(P.rank.value))))
        P.best.on_click(lambda _: self.pick(0))
        P.scene_mode.on_update(lambda _: display.redraw_chosen())
        P.heatmap_mode.on_update(lambda _: display.heatmap_mode_changed())
        P.visibility.on_click(lambda event: self.toggle(event.target.value))
        P.max_particles.on_update(self.drawn_changed)
        P.load.on_click(lambda _: self.load_typed())
        P.camera.on_click(lambda event: self.cameras.preset(self.state.view, event.target.value, event.client))
        self.server.on_client_connect(self.cameras.client_connected)
        P.demo.on_click(lambda _: self.load(p.Source(demo=True)))

    def drawn_changed(self, event) -> None:
        """Particles drawn: the engine sends that many; once the user sets it (a client's event), frames keep it."""
        self.drawn_by_user |= event.client is not None
        self.send(p.SetDisplay(int(self.panel.max_particles.value)))

    def send(self, cmd) -> None:
        self.engine.send(cmd)

    @property
    def config(self) -> EstimatorConfig:
        """The settings the run uses."""
        return self.settings.config

    def toggle(self, option: str) -> None:
        """A click on the visibility bar."""
        with self.lock:
            self.display.toggle(visibility_item(option))

    def run(self) -> None:
        with self.lock:
            self.settings.revert()
        self.send(p.Run(self.panel.stop_on_convergence.value))

    def on_truth(self, msg: p.TruthErrors) -> None:
        self.state.truth = msg
        self.panel.truth.content = truth_markdown(msg.iteration, msg.rows, self.display.names)

    def on_failure(self, failure: p.Failure) -> None:
        if failure.topic not in ("labels", "session"):
            self.stepper.done()
        self.reporter.report(failure)

    def pause(self) -> None:
        # Sent under the lock, so it reaches the engine before the Shown of any later iteration (on_snapshot sends
        # that under the lock too): the run stops at most one iteration after the one on display.
        with self.lock:
            self.state.pause_requested_at = self.state.iteration
            self.send(p.Pause())

    def reset(self) -> None:
        self.reporter.guarded(lambda: self.send(self.settings.for_reset()))

    def load(self, source: p.Source) -> None:
        self.panel.title.content = f"**workbench** · loading {source.describe()} …"
        self.settings.likelihood = self.panel.likelihood.value
        self.send(p.Load(source, self.config, self.settings.likelihood))
        self.settings.show_pending()

    def load_typed(self) -> None:
        def apply():
            text = self.panel.dataset.value.strip()
            if not text:
                raise InputError("Dataset", "type the path of a BOP dataset folder")
            scene_id, im_id = self.panel.frame_ids()
            self.load(p.Source(dataset=Path(text).expanduser(), scene_id=scene_id, im_id=im_id))

        self.reporter.guarded(apply)

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
                p.Failure: self.on_failure,
                p.Workers: self.reporter.on_workers,
                p.Labels: self.labelling.show_labels,
                p.LabelHeatmap: self.labelling.show_heatmap,
                p.LabelErrors: self.labelling.show_errors,
                p.TruthErrors: self.on_truth,
                p.Saved: self.reporter.on_saved,
                p.SessionQuestion: self.sessions.on_question,
                p.SessionRestored: self.on_session_restored,
                p.SequenceState: self.sequence.show,
            }[type(msg)]
            try:
                handler(msg)
            except Exception as err:  # a drawing bug must not stop the messages that follow
                self.reporter.drawing_failed(type(msg).__name__, err)
            finally:
                self.changed.notify_all()

    def on_ready(self, msg: p.Ready) -> None:
        self.state.engine_pid = msg.pid

    def on_loaded(self, msg: p.Loaded) -> None:
        view, P = msg.view, self.panel
        self.source = msg.source  # what a restarted engine reloads
        old = self.state
        self.state = replace(RunView(), view=view, engine_pid=old.engine_pid, restarts=old.restarts,
                             failures=old.failures, display_errors=old.display_errors)
        with self.server.atomic():
            P.title.content = f"**workbench** · {view.title}"
            P.error.visible = False
            if not self.drawn_by_user:  # the frame's share of the outlines drawn (sends SetDisplay)
                P.max_particles.value = default_drawn(len(view.meshes))
            self.display.set_frame(view)
            self.labelling.set_frame(view)
            self.sessions.on_frame(view.title)
        if not msg.keep_camera:  # another frame of a sequence: the same table frame, the user's view
            self.cameras.preset(view, FRAME_OBJECTS, None)

    def on_snapshot(self, msg: p.Snapshot) -> None:
        s, P = self.state, self.panel
        if s.reports and s.reports[-1]["iteration"] == msg.report["iteration"]:
            s.reports.pop()  # a republished iteration (e.g. more particles drawn), not a new one
        s.reports.append(msg.report)
        s.cloud, s.iteration, s.running = msg.cloud, msg.report["iteration"], msg.running
        self.send(p.Shown(s.iteration))  # the engine may start the next iteration (see protocol.Shown)
        self.display.show_cloud(msg.cloud, msg.posterior, defer=msg.running)
        self.display.show_posterior(msg.posterior, s.iteration, defer=msg.running)
        P.rank.max = max(1, msg.cloud.n_total - 1)
        self.reporter.clear_error()  # an iteration went through: whatever failed before was dealt with
        P.plots.add(msg.report, msg.cloud.n_total, self.config.converge_position, self.config.converge_degrees)
        P.timings.content = timings_markdown(msg.report)
        P.status.content = status_markdown(self.state, self.config)

    def on_chosen(self, msg: p.Chosen) -> None:
        self.state.chosen = msg
        self.display.show_chosen(msg, defer=self.state.running)

    def on_run_state(self, msg: p.RunState) -> None:
        s, P = self.state, self.panel
        s.last_state, s.running = msg, msg.running
        self.stepper.done()
        if msg.reason == "reset":
            s.reports, s.cloud, s.chosen, s.iteration, s.truth, s.run_config = [], None, None, -1, None, None
            self.display.reset()
        elif not msg.running:
            self.display.throttle.flush()  # the run stopped: show where it stopped now
        P.run.disabled = msg.running
        P.pause.disabled = not msg.running
        P.step.disabled = msg.running
        P.status.content = status_markdown(self.state, self.config)

    def on_session_restored(self, msg: p.SessionRestored) -> None:
        """Show the restored run's settings and history (its frame came in ``Loaded`` just before)."""
        self.settings.config, self.settings.likelihood = msg.config, msg.likelihood
        with self.quiet:  # the engine has these settings already; showing them must not send them back
            self.panel.show_config(msg.config, msg.likelihood)
        self.show_history(msg.reports)
        self.settings.show_pending()
        self.sessions.on_restored(msg)

    def show_history(self, reports: list[dict], run_config: EstimatorConfig | None = None) -> None:
        """A run's iterations at once (a restored session; a frame of a sequence put on show, whose run may have
        settings of its own, ``run_config``): the plots and the status line."""
        s, cfg = self.state, run_config or self.config
        s.reports, s.run_config = list(reports), run_config
        s.iteration = reports[-1]["iteration"] if reports else -1
        self.panel.plots.set_history(reports, cfg.particles, cfg.converge_position, cfg.converge_degrees)
        self.panel.status.content = status_markdown(s, self.config)

    def on_engine_died(self, exitcode: int | None, gave_up: bool) -> None:
        self.stepper.done()
        with self.lock:
            self.state.restarts += 1
            source = self.source
        self.reporter.engine_died(exitcode, gave_up, reloading=source is not None)
        if source is not None and not gave_up:
            self.send(p.Load(source, self.config, self.panel.likelihood.value))

    # -- lifetime

    def stop(self) -> None:
        self.settings.cancel()
        self.display.throttle.cancel()
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
    and then stop; else return the handle at once. ``ray`` (a evaluation.ray.RayConfig): evaluate each batch on
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
