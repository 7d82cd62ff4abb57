"""The browser workbench: a viser server showing one estimation run, driven from its control panel.

    workbench serve [DATASET --scene ID --frame ID | --demo | --session PATH] [--sessions-dir DIR]
                    [--host 127.0.0.1] [--port 8080]

The estimator lives in a separate process (``engine.py``); this process only draws. GUI and scene are viser's
server-wide ones, so every open tab sees and drives the same run. Messages from the engine arrive on a reader
thread and GUI callbacks on viser's threads: both are handed to one UI thread (``ui_thread``), which runs them
one at a time.
"""

from __future__ import annotations

import errno
import socket
import time
from dataclasses import dataclass, replace
from pathlib import Path

import viser

from workbench.app import protocol as p
from workbench.app.engine.engine import DEMO_DIR
from workbench.app.engine.process import EngineClient
from workbench.app.ui.data_tab import DataTab
from workbench.app.ui.labelling.labelling import Labelling
from workbench.app.ui.reporting import Reporter
from workbench.app.ui.run.buttons import RunButtons
from workbench.app.ui.run.camera import FRAME_OBJECTS, TabCameras
from workbench.app.ui.run.display import RunDisplay
from workbench.app.ui.run.plots import Plots
from workbench.app.ui.run.settings import SettingsForm
from workbench.app.ui.run.status import RunView, status_markdown, timings_markdown
from workbench.app.ui.run.truth import truth_markdown
from workbench.app.ui.run.view_box import ViewBox, visibility_item
from workbench.app.ui.sequence.panel import SequencePanel
from workbench.app.ui.sessions.panel import Sessions
from workbench.app.ui.ui_thread import UiThread, on_ui_thread
from workbench.app.ui.widgets.quiet import Quiet
from workbench.errors import InputError
from workbench.inference.config import EstimatorConfig
from workbench.physics.config import PhysicsConfig

# Small enough for one software-rendered machine to iterate at a few Hz; the panel changes it.
DEFAULT_CONFIG = EstimatorConfig(particles=128, iterations=60)
SESSIONS_DIR = Path("sessions")
TABS = (("Estimator", viser.Icon.ADJUSTMENTS), ("Inspect", viser.Icon.ZOOM_IN), ("Plots", viser.Icon.CHART_LINE),
        ("Data", viser.Icon.DATABASE), ("Label", viser.Icon.PENCIL), ("Sessions", viser.Icon.DEVICE_FLOPPY))


class App:
    """One run shown in every browser tab: the panel's commands go to the engine process, its messages come back
    here. Drawing them is ``display``'s job, telling the user about failures and restarts ``reporter``'s."""

    def __init__(self, server: viser.ViserServer, source: p.Source | None, workers: int,
                 config: EstimatorConfig = DEFAULT_CONFIG, likelihood: str = "robust",
                 sessions_dir: Path = SESSIONS_DIR, session: Path | None = None, ray=None,
                 physics: PhysicsConfig = PhysicsConfig()):
        self.server = server
        self.ui = UiThread()  # runs every GUI callback and engine message, one at a time: no module takes a lock
        self.quiet = Quiet()  # set while the server itself writes controls: their callbacks must not echo
        self.source: p.Source | None = None  # the last frame the engine loaded
        self.state = RunView()
        self.cameras = TabCameras(server, self.ui)
        # Each part of the panel builds and keeps its own handles, in the panel's order from the top.
        gui = server.gui
        gui.configure_theme(control_width="large", dark_mode=False, show_logo=False, show_share_button=False)
        self.reporter = Reporter(server, lambda: self.state)
        self.buttons = RunButtons(gui, self.ui, self.send, lambda: self.state.running, lambda: self.settings.revert(),
                                  on_run=self.run, on_pause=self.pause, on_reset=self.reset)
        self.view_box = ViewBox(gui)
        tabs = gui.add_tab_group()
        tab = {name: tabs.add_tab(name, icon) for name, icon in TABS}
        self.settings = SettingsForm(gui, tab["Estimator"], self.ui, self.quiet, self.reporter, self.send, config,
                                     likelihood)
        self.labelling = Labelling(server, tab["Label"], self.send, self.ui, self.quiet, self.reporter,
                                   on_heatmap_mode=lambda: self.display.label_heatmap_mode_changed())
        self.display = RunDisplay(server, tab["Inspect"], self.ui, self.quiet, self.reporter, self.view_box,
                                  self.labelling, config.particles, self.send)
        self.plots = Plots(gui, tab["Plots"], self.ui)
        self.data = DataTab(gui, tab["Data"])
        with tab["Data"]:
            self.sequence = SequencePanel(gui, self.data.sequence_order, self.ui, self.send, self.show_history,
                                          names=lambda: self.display.names)
        self.sessions = Sessions(gui, tab["Sessions"], sessions_dir, self.send, self.ui, self.quiet,
                                 iteration=lambda: self.state.iteration)
        self.reporter.topics.update({"session": self.sessions.on_failure, "labels": self.labelling.show_failure,
                                     "sequence": self.sequence.on_failure,
                                     "sequence labels": self.labelling.sequence.on_failure})
        self._wire()
        self.engine = EngineClient(workers, lambda msg: self.ui.call(self.on_message, msg),
                                   lambda code, gave_up: self.ui.call(self.on_engine_died, code, gave_up), ray=ray,
                                   physics=physics)
        self.ui.call(self._start, source, session)

    def _start(self, source: p.Source | None, session: Path | None) -> None:
        if session is not None:
            # As the Sessions tab's Load: the engine asks first if the dataset changed; a bad file is a message.
            self.reporter.set_title(f"loading session {session} …")
            self.sessions.load_path(session)
        elif source is not None:
            self.load(source)

    # -- commands from the panel

    def _wire(self) -> None:
        """The controls whose actions reach beyond their own part of the panel."""
        on_ui, V, D = self.ui.callback, self.view_box, self.data
        V.visibility.on_click(on_ui(lambda event: self.toggle(event.target.value)))
        V.camera.on_click(on_ui(lambda event: self.cameras.preset(self.state.view, event.target.value, event.client,
                                                                  self.labelling.editor.estimate)))
        self.server.on_client_connect(on_ui(self.cameras.client_connected))
        D.load.on_click(on_ui(lambda _: self.load_typed()))
        D.demo.on_click(on_ui(lambda _: self.load(p.Source(demo=True))))

    def send(self, cmd) -> None:
        self.engine.send(cmd)

    @property
    def config(self) -> EstimatorConfig:
        """The settings the run uses."""
        return self.settings.config

    @on_ui_thread
    def toggle(self, option: str) -> None:
        """A click on the visibility bar."""
        self.display.toggle(visibility_item(option))

    @on_ui_thread
    def run(self) -> None:
        self.settings.revert()
        self.send(p.Run(self.settings.tab.stop_on_convergence.value))

    def on_truth(self, msg: p.TruthErrors) -> None:
        self.state.truth = msg
        self.view_box.truth.content = truth_markdown(msg.iteration, msg.rows, self.display.names)

    def on_failure(self, failure: p.Failure) -> None:
        if failure.topic not in ("labels", "session", "sequence labels"):
            self.buttons.done()
        self.reporter.report(failure)

    @on_ui_thread
    def pause(self) -> None:
        # Sent from the UI thread, so it reaches the engine before the Shown of any later iteration (on_snapshot
        # sends that from the UI thread too): the run stops at most one iteration after the one on display.
        self.state.pause_requested_at = self.state.iteration
        self.send(p.Pause())
        self.buttons.pause.disabled = True  # taken: the status says the run stops after this iteration
        self.buttons.status.content = status_markdown(self.state, self.config)

    @on_ui_thread
    def reset(self) -> None:
        # The settings are read first: a refused one is reported and nothing is sent (nor said to wait).
        self.reporter.guarded(lambda: self.buttons.press_reset(self.settings.for_reset()))

    @on_ui_thread
    def load(self, source: p.Source) -> None:
        self.reporter.set_title(f"loading {source.describe()} …")
        self.settings.likelihood = self.settings.tab.likelihood.value
        self.send(p.Load(source, self.config, self.settings.likelihood))
        # Until the engine has the frame (its new run's reset, or a failure): a Step or Run clicked meanwhile would
        # wait in the engine's queue with no sign of it.
        self.buttons.wait("Loading the frame")
        self.settings.show_pending()

    @on_ui_thread
    def load_typed(self) -> None:
        def apply():
            text = self.data.dataset.value.strip()
            if not text:
                raise InputError("Dataset", "type the path of a BOP dataset folder")
            scene_id, im_id = self.data.frame_ids()
            self.load(p.Source(dataset=Path(text).expanduser(), scene_id=scene_id, im_id=im_id))

        self.reporter.guarded(apply)

    @on_ui_thread
    def pick(self, rank: int) -> None:
        """Choose the particle at ``rank`` (as a click on it does)."""
        self.display.pick(rank)

    # -- messages from the engine

    def on_message(self, msg) -> None:
        handler = {
            p.Ready: self.on_ready,
            p.Loaded: self.on_loaded,
            p.Snapshot: self.on_snapshot,
            p.Chosen: self.on_chosen,
            p.RunState: self.on_run_state,
            p.Stage: self.on_stage,
            p.Failure: self.on_failure,
            p.Workers: self.on_workers,
            p.Labels: self.labelling.show_labels, p.LabelHeatmap: self.labelling.show_heatmap,
            p.LabelErrors: self.labelling.show_errors, p.Backups: self.labelling.backups.show,
            p.TruthErrors: self.on_truth, p.TruthReloaded: self.display.truth_reloaded,
            p.Saved: self.on_saved,
            p.SessionQuestion: self.sessions.on_question,
            p.SessionRestored: self.on_session_restored,
            p.SequenceState: self.on_sequence,
            p.SequenceLabelState: self.labelling.sequence.show,
            p.SequenceLabelProgress: self.labelling.sequence.show_progress,
            p.SequenceLabelsDone: self.labelling.sequence.done,
        }[type(msg)]
        try:
            handler(msg)
        except Exception as err:  # a drawing bug must not stop the messages that follow
            self.reporter.drawing_failed(type(msg).__name__, err)

    def on_ready(self, msg: p.Ready) -> None:
        self.state.engine_pid = msg.pid

    def on_workers(self, msg: p.Workers) -> None:
        self.reporter.on_workers(msg)
        self.data.show_workers(msg.pids, self.state.restarts)

    def on_sequence(self, msg: p.SequenceState) -> None:
        self.sequence.show(msg)
        self.labelling.sequence.show_sequence(msg)

    def on_saved(self, msg: p.Saved) -> None:
        show = {"session": self.sessions.on_saved, "sequence labels": self.labelling.sequence.show_saved}
        show.get(msg.kind, self.labelling.show_saved)(msg)
        self.reporter.on_saved(msg)

    def on_loaded(self, msg: p.Loaded) -> None:
        view = msg.view
        self.source = msg.source  # what a restarted engine reloads
        old = self.state
        self.state = replace(RunView(), view=view, engine_pid=old.engine_pid, restarts=old.restarts,
                             failures=old.failures, display_errors=old.display_errors)
        with self.server.atomic():
            self.reporter.set_title(view.title)
            self.reporter.error.visible = False
            self.display.set_frame(view)
            self.data.show_frame(view)
            self.clear_run_tables()
            self.labelling.set_frame(view)
            self.sessions.on_frame(view.title)
        if not msg.keep_camera:  # another frame of a sequence: the same table frame, the user's view
            self.cameras.preset(view, FRAME_OBJECTS, None)

    def on_snapshot(self, msg: p.Snapshot) -> None:
        s = self.state
        if s.reports and s.reports[-1]["iteration"] == msg.report["iteration"]:
            s.reports.pop()  # a republished iteration (e.g. more particles drawn), not a new one
        s.reports.append(msg.report)
        s.cloud, s.iteration, s.running = msg.cloud, msg.report["iteration"], msg.running
        self.send(p.Shown(s.iteration))  # the engine may start the next iteration (see protocol.Shown)
        self.display.show_cloud(msg.cloud, msg.posterior, defer=msg.running)
        self.display.show_posterior(msg.posterior, s.iteration, defer=msg.running)
        self.display.inspect.rank.max = max(1, msg.cloud.n_total - 1)
        self.reporter.clear_error()  # an iteration went through: whatever failed before was dealt with
        self.plots.add(msg.report, msg.cloud.n_total, self.config.converge_position, self.config.converge_degrees)
        self.settings.tab.timings.content = timings_markdown(msg.report)
        self.buttons.status.content = status_markdown(self.state, self.config)

    def on_stage(self, msg: p.Stage) -> None:
        self.state.stage = msg
        self.buttons.status.content = status_markdown(self.state, self.config)

    def on_chosen(self, msg: p.Chosen) -> None:
        self.state.chosen = msg
        self.display.show_chosen(msg, defer=self.state.running)

    def on_run_state(self, msg: p.RunState) -> None:
        s = self.state
        s.last_state, s.running = msg, msg.running
        s.stage = None  # a stage is what a run is doing; it starts, stops or is reset here
        if msg.running:
            s.pause_requested_at = None  # a new run: no Pause pressed in it yet
        self.buttons.done()
        if msg.reason == "reset":
            s.reports, s.cloud, s.chosen, s.iteration, s.truth, s.run_config = [], None, None, -1, None, None
            self.display.reset()
            self.clear_run_tables()
        elif not msg.running:
            self.display.throttle.flush()  # the run stopped: show where it stopped now
        self.buttons.show_running(msg.running)
        self.buttons.status.content = status_markdown(self.state, self.config)

    def clear_run_tables(self) -> None:
        """No plots, timings or truth of an old run (a new frame, or a reset)."""
        self.plots.clear()
        self.settings.tab.timings.content = ""
        self.view_box.truth.content = ""

    def on_session_restored(self, msg: p.SessionRestored) -> None:
        """Show the restored run's settings and history (its frame came in ``Loaded`` just before)."""
        self.settings.config, self.settings.likelihood = msg.config, msg.likelihood
        with self.quiet:  # the engine has these settings already; showing them must not send them back
            self.settings.tab.show_config(msg.config, msg.likelihood)
        self.show_history(msg.reports)
        self.settings.show_pending()
        self.sessions.on_restored(msg)

    def show_history(self, reports: list[dict], run_config: EstimatorConfig | None = None) -> None:
        """A run's iterations at once (a restored session; a frame of a sequence put on show, whose run may have
        settings of its own, ``run_config``): the plots and the status line."""
        s, cfg = self.state, run_config or self.config
        s.reports, s.run_config = list(reports), run_config
        s.iteration = reports[-1]["iteration"] if reports else -1
        self.plots.set_history(reports, cfg.particles, cfg.converge_position, cfg.converge_degrees)
        self.buttons.status.content = status_markdown(s, self.config)

    def on_engine_died(self, exitcode: int | None, gave_up: bool) -> None:
        self.buttons.done()
        self.labelling.sequence.done()
        self.state.restarts += 1
        self.reporter.engine_died(exitcode, gave_up, reloading=self.source is not None)
        if self.source is not None and not gave_up:
            self.send(p.Load(self.source, self.config, self.settings.tab.likelihood.value))

    # -- lifetime

    def stop(self) -> None:
        self.ui.call(lambda: (self.settings.cancel(), self.display.throttle.cancel()))
        self.engine.stop()
        self.ui.stop()

    def wait_for(self, predicate, timeout: float) -> bool:
        """Block until ``predicate(self.state)`` holds (checked after each UI task, in the caller's thread), or the
        timeout."""
        return self.ui.wait_until(lambda: predicate(self.state), timeout)


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
    physics: PhysicsConfig = PhysicsConfig(),
) -> AppHandle:
    """Start the workbench on ``host:port`` (localhost unless told otherwise) with ``dataset``'s frame, or the demo
    (``demo``, or no dataset), or continuing the saved ``session`` (a session JSON file). Sessions are saved to and
    listed from ``sessions_dir`` (default: the session's folder, else ./sessions). ``block``: serve until Ctrl-C
    and then stop; else return the handle at once. ``ray`` (a evaluation.ray.RayConfig): evaluate each batch on
    ``workers`` Ray actors instead of local processes, with the same results. ``physics``: how the frames loaded
    are simulated (``PhysicsConfig.backend``: Bullet or MuJoCo); a session keeps its own.

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
              None if session is None else Path(session), ray=ray, physics=physics)
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
