"""The control panel: every GUI handle of the workbench, built once on the server's shared GUI so that all
browser tabs see (and drive) the same run. Wiring the handles to actions is ``server.App``'s job."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import viser

from workbench.app.engine.snapshot import DEFAULT_DISPLAY
from workbench.app.ui.labelling.controls import LabelTab, build_label_tab
from workbench.app.ui.run.camera import FRAME_OBJECTS, FROM_SENSOR
from workbench.app.ui.run.modes import NO_POSTERIOR
from workbench.app.ui.run.plots import Plots
from workbench.app.ui.run.views import HEATMAP_MODES, SCENE_MODES
from workbench.app.ui.sequence.panel import SequenceTab, build_sequence_tab
from workbench.app.ui.sessions.panel import SessionsTab, build_sessions_tab
from workbench.app.ui.ui_thread import UiThread
from workbench.app.ui.widgets.layout import button_row_css
from workbench.errors import InputError
from workbench.inference.config import EstimatorConfig
from workbench.inference.smc.particles import Sigma

METHOD_LABELS = {"PI-PF": "pipf", "PI-MCPF": "mcpf"}
LIKELIHOODS = ("robust", "ssd")
DEFAULT_DRAWN = DEFAULT_DISPLAY


@dataclass
class Panel:
    title: viser.GuiMarkdownHandle
    error: viser.GuiMarkdownHandle
    field_style: viser.GuiHtmlHandle  # a <style> outlining the fields whose typed value was refused
    status: viser.GuiMarkdownHandle
    busy: viser.GuiMarkdownHandle  # "Step running · 3 s" while a Step is out
    busy_bar: viser.GuiProgressBarHandle  # its spinner
    view_legend: viser.GuiHtmlHandle
    camera: viser.GuiButtonGroupHandle
    visibility: viser.GuiButtonGroupHandle  # the visibility bar: one toggle per layer (SHOW_ITEMS)
    truth: viser.GuiMarkdownHandle  # the estimate against the dataset's ground truth
    step: viser.GuiButtonHandle
    run: viser.GuiButtonHandle
    pause: viser.GuiButtonHandle
    reset: viser.GuiButtonHandle
    # Estimator
    method: viser.GuiDropdownHandle
    # Text, not number inputs: a number input silently empties itself on "abc" and keeps the old value unseen.
    particles: viser.GuiTextHandle
    iterations: viser.GuiTextHandle
    sigma_xy: viser.GuiTextHandle  # "x, y" in cm
    sigma_z: viser.GuiTextHandle
    sigma_angles: viser.GuiTextHandle  # "roll, pitch, yaw" in degrees
    likelihood: viser.GuiDropdownHandle
    seed: viser.GuiTextHandle
    pending: viser.GuiMarkdownHandle  # what applies at Reset, and what is waiting for it
    stop_on_convergence: viser.GuiCheckboxHandle
    timings: viser.GuiMarkdownHandle
    # Inspect
    posterior: viser.GuiMarkdownHandle  # the settled estimate's confidence and other modes, per object
    rank: viser.GuiSliderHandle
    best: viser.GuiButtonHandle
    scene_mode: viser.GuiDropdownHandle
    physics_change: viser.GuiMarkdownHandle
    heatmap_mode: viser.GuiDropdownHandle
    legend: viser.GuiHtmlHandle
    heat_image: viser.GuiImageHandle
    max_particles: viser.GuiNumberHandle
    # Plots
    plots: Plots
    # Data
    dataset: viser.GuiTextHandle
    scene_id: viser.GuiTextHandle
    im_id: viser.GuiTextHandle
    load: viser.GuiButtonHandle
    demo: viser.GuiButtonHandle
    sequence: SequenceTab  # Next frame, the timeline and the plots across frames, where the scene has several
    depth_image: viser.GuiImageHandle
    depth_legend: viser.GuiHtmlHandle
    rgb_image: viser.GuiImageHandle
    workers: viser.GuiMarkdownHandle
    # Label, Sessions
    label: LabelTab
    label_rgb: viser.GuiImageHandle
    sessions: SessionsTab
    shown: dict[str, bool] = field(default_factory=lambda: dict(SHOWN_BY_DEFAULT))

    def show(self, item: str) -> bool:
        return self.shown[item]

    def set_shown(self, item: str, on: bool) -> None:
        """Record a layer's visibility and relabel its toggle (the caller draws the change)."""
        self.shown[item] = bool(on)
        options = visibility_options(self.shown)
        if tuple(self.visibility.options) != options:
            self.visibility.options = options

    def estimator_config(self, base: EstimatorConfig) -> EstimatorConfig:
        """The controls' values over ``base`` (which keeps the settings the panel does not show); InputError
        naming every refused field (``read_config`` for the config and the errors apart)."""
        config, errors = self.read_config(base)
        if errors:
            raise InputError(", ".join(errors), "; ".join(f"{k}: {v}" for k, v in errors.items()))
        return config

    def read_config(self, base: EstimatorConfig) -> tuple[EstimatorConfig, dict[str, str]]:
        """-> (``base`` with every valid field's value, {field label: problem} of the refused ones, which keep
        ``base``'s value)."""
        s, deg, errors = base.sigma, 180.0 / np.pi, {}

        def read(handle, parse, fallback):
            try:
                return parse(handle.value)
            except InputError as err:
                errors[FIELD_LABELS[id(handle)] if id(handle) in FIELD_LABELS else str(err.path)] = err.problem
                return fallback

        # A sigma shown as it was set (to the 6 digits shown) keeps base's exact value: cm and degrees do not
        # round-trip to the last bit, and a restored session must step with exactly its saved sigma.
        def exact(shown, value, scale):
            return value if abs(shown - value * scale) <= 1e-6 * abs(value * scale) + 1e-12 else shown / scale

        sx, sy = read(self.sigma_xy, lambda t: numbers(t, SIGMA_XY, 2, "cm"), (s.x * 100, s.y * 100))
        (sz,) = read(self.sigma_z, lambda t: numbers(t, SIGMA_Z, 1, "cm"), (s.z * 100,))
        roll, pitch, yaw = read(self.sigma_angles, lambda t: numbers(t, SIGMA_ANGLES, 3, "°"),
                                (s.roll * deg, s.pitch * deg, s.yaw * deg))
        config = replace(
            base,
            method=METHOD_LABELS[self.method.value],
            particles=read(self.particles, lambda t: whole_number(t, "Particles", 1, 100_000), base.particles),
            iterations=read(self.iterations, lambda t: whole_number(t, "Iterations", 0, 100_000), base.iterations),
            sigma=Sigma(x=exact(sx, s.x, 100.0), y=exact(sy, s.y, 100.0), z=exact(sz, s.z, 100.0),
                        roll=exact(roll, s.roll, deg), pitch=exact(pitch, s.pitch, deg), yaw=exact(yaw, s.yaw, deg)),
            seed=read(self.seed, lambda t: whole_number(t, "Seed", 0, 2**32 - 1), base.seed),
        )
        config.validate()
        return config, errors

    def revert(self, labels, config: EstimatorConfig) -> None:
        """Put ``config``'s values back into the fields labelled ``labels`` (call inside ``Quiet``)."""
        s, deg = config.sigma, 180.0 / np.pi
        values = {
            "Particles": (self.particles, str(config.particles)),
            "Iterations": (self.iterations, str(config.iterations)),
            SIGMA_XY: (self.sigma_xy, shown_numbers(s.x * 100, s.y * 100)),
            SIGMA_Z: (self.sigma_z, shown_numbers(s.z * 100)),
            SIGMA_ANGLES: (self.sigma_angles, shown_numbers(s.roll * deg, s.pitch * deg, s.yaw * deg)),
            "Seed": (self.seed, str(config.seed)),
        }
        for label in labels:
            if label in values:
                handle, text = values[label]
                handle.value = text

    def outline(self, labels) -> None:
        """Outline the fields labelled ``labels`` in red (none: clear), by their labels' ``for`` ids."""
        ids = [self.field_ids[k] for k in labels if k in self.field_ids]
        css = "".join(
            f'.mantine-Flex-root:has(label[for="{i}"]) input{{outline:2px solid #e03131;outline-offset:-1px}}'
            f'label[for="{i}"]{{color:#e03131;font-weight:600}}' for i in ids)
        content = f"<style>{css}</style>" if css else ""
        if self.field_style.content != content:
            self.field_style.content = content

    @property
    def field_ids(self) -> dict[str, str]:
        return {FIELD_LABELS[id(h)]: h._impl.uuid for h in (self.particles, self.iterations, self.sigma_xy,
                                                             self.sigma_z, self.sigma_angles, self.seed)}

    def show_config(self, config: EstimatorConfig, likelihood: str) -> None:
        """Put ``config`` into the controls (call inside ``Quiet``: these writes fire the controls' callbacks)."""
        self.method.value = {v: k for k, v in METHOD_LABELS.items()}[config.method]
        self.revert(("Particles", "Iterations", SIGMA_XY, SIGMA_Z, SIGMA_ANGLES, "Seed"), config)
        self.likelihood.value = likelihood

    def frame_ids(self) -> tuple[int | None, int | None]:
        """The scene and frame typed in the Data tab; empty means the dataset's first."""
        out = []
        for handle, what in ((self.scene_id, "scene id"), (self.im_id, "frame id")):
            text = handle.value.strip()
            try:
                out.append(int(text) if text else None)
            except ValueError:
                raise InputError(what, f"must be a whole number (or empty for the first), got {text!r}") from None
        return out[0], out[1]


def whole_number(text: str, field: str, lo: int, hi: int) -> int:
    """A typed whole number in [lo, hi]; InputError naming the field otherwise."""
    try:
        value = int(str(text).strip())
    except ValueError:
        raise InputError(field, f"must be a whole number from {lo} to {hi}, got {str(text)!r}") from None
    if not lo <= value <= hi:
        raise InputError(field, f"must be a whole number from {lo} to {hi}, got {value}")
    return value


def numbers(text: str, field: str, n: int, unit: str) -> tuple[float, ...]:
    """``n`` comma-separated numbers, each finite and >= 0, in the field's unit; InputError naming the field."""
    parts = [t.strip() for t in str(text).replace(";", ",").split(",")]
    try:
        values = tuple(float(t) for t in parts)
    except ValueError:
        values = ()
    if len(values) != n or not all(np.isfinite(v) and v >= 0 for v in values):
        what = "a number" if n == 1 else f"{n} numbers separated by commas, each"
        raise InputError(field, f"must be {what} >= 0 {unit}, got {str(text).strip()!r}")
    return values


def shown_numbers(*values: float) -> str:
    return ", ".join(f"{v:.6g}" for v in values)


SIGMA_XY, SIGMA_Z, SIGMA_ANGLES = "σ x, y (cm)", "σ elevation (cm)", "σ roll, pitch, yaw (°)"
FIELD_LABELS: dict[int, str] = {}  # id(handle) -> its label, for the typed fields
# The visibility bar: one toggle per layer of the 3D view, and what is shown at first.
SHOW_ITEMS = ("points", "particles", "estimate", "modes", "truth", "labels", "heatmap")
SHOWN_BY_DEFAULT = {"points": True, "particles": True, "estimate": True, "modes": True, "truth": True,
                    "labels": True, "heatmap": False}
ON, OFF = "●", "○"


def visibility_options(shown: dict[str, bool]) -> tuple[str, ...]:
    """The bar's buttons: "● points" while shown, "○ points" while hidden."""
    return tuple(f"{ON if shown[k] else OFF} {k}" for k in SHOW_ITEMS)


def visibility_item(option: str) -> str:
    """A clicked button's layer: "● points" -> "points"."""
    return option.split(" ", 1)[-1]


def build_panel(gui: viser.GuiApi, ui: UiThread, config: EstimatorConfig, likelihood: str) -> Panel:
    gui.configure_theme(control_width="large", dark_mode=False, show_logo=False, show_share_button=False)
    # The fixed top is kept short: title, status, the actions, then the View box; the rest lives in tabs.
    title = gui.add_markdown("**workbench** · nothing loaded")
    error = gui.add_markdown("", visible=False)
    field_style = gui.add_html("")
    status = gui.add_markdown("No iterations yet.")
    busy = gui.add_markdown("", visible=False)
    busy_bar = gui.add_progress_bar(100.0, animated=True, visible=False)
    step = gui.add_button("Step", icon=viser.Icon.PLAYER_TRACK_NEXT, hint="one iteration")
    run = gui.add_button("Run", icon=viser.Icon.PLAYER_PLAY, color="green",
                         hint="iterate until the budget, convergence or Pause")
    pause = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE, disabled=True, hint="stop after this iteration")
    reset = gui.add_button("Reset", icon=viser.Icon.REFRESH, color="gray",
                           hint="new random particles (seed and likelihood model apply here)")
    gui.add_html(button_row_css([b._impl.uuid for b in (step, run, pause, reset)]))  # one row: a short top
    # The 3D view's camera presets, what it shows, the estimate's error against the truth, and its one legend.
    with gui.add_folder("View", expand_by_default=True):
        camera = gui.add_button_group("Camera", (FRAME_OBJECTS, FROM_SENSOR))
        visibility = gui.add_button_group("Show", visibility_options(SHOWN_BY_DEFAULT))
        truth = gui.add_markdown("")
        with gui.add_folder("Legend", expand_by_default=False):
            view_legend = gui.add_html("")
    tabs = gui.add_tab_group()

    with tabs.add_tab("Estimator", viser.Icon.ADJUSTMENTS):
        method = gui.add_dropdown("Method", tuple(METHOD_LABELS),
                                  initial_value={v: k for k, v in METHOD_LABELS.items()}[config.method],
                                  hint="applies at the next step")
        particles = gui.add_text("Particles", str(config.particles), hint="1 to 100000; applies at the next step")
        iterations = gui.add_text("Iterations", str(config.iterations), hint="the budget Run stops at")
        s, deg = config.sigma, 180.0 / np.pi
        sigma_xy = gui.add_text(SIGMA_XY, shown_numbers(s.x * 100, s.y * 100),
                                hint="diffusion of the position on the table: x, y; applies at the next step")
        sigma_z = gui.add_text(SIGMA_Z, shown_numbers(s.z * 100), hint="applies at the next step")
        sigma_angles = gui.add_text(SIGMA_ANGLES, shown_numbers(s.roll * deg, s.pitch * deg, s.yaw * deg),
                                    hint="roll, pitch, yaw; applies at the next step")
        like = gui.add_dropdown("Likelihood", LIKELIHOODS, initial_value=likelihood, hint="applies at Reset")
        seed = gui.add_text("Seed", str(config.seed), hint="a whole number >= 0; applies at Reset")
        pending = gui.add_markdown(RESET_NOTE)
        stop = gui.add_checkbox("Stop at convergence", True)
        timings = gui.add_markdown("")
    for handle, label in ((particles, "Particles"), (iterations, "Iterations"), (sigma_xy, SIGMA_XY),
                          (sigma_z, SIGMA_Z), (sigma_angles, SIGMA_ANGLES), (seed, "Seed")):
        FIELD_LABELS[id(handle)] = label

    with tabs.add_tab("Inspect", viser.Icon.ZOOM_IN):
        posterior = gui.add_markdown(NO_POSTERIOR)
        rank = gui.add_slider("Particle rank", 0, max(1, config.particles - 1), 1, 0,
                              hint="0 = most likely; or click a particle in the 3D view")
        best = gui.add_button("Most likely", icon=viser.Icon.STAR)
        scene_mode = gui.add_dropdown("Physics", SCENE_MODES, initial_value="before + after",
                                      hint="the chosen particle before and after physics projection")
        physics_change = gui.add_markdown("")
        heatmap_mode = gui.add_dropdown("Heatmap", HEATMAP_MODES, initial_value="off",
                                        hint="the chosen particle's fit per pixel, drawn on the observed points")
        legend = gui.add_html("")
        heat_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="chosen particle, problem grid",
                                   format="png", visible=False)
        max_particles = gui.add_number("Particles drawn", DEFAULT_DRAWN, min=1, max=20_000, step=1,
                                       hint="the most likely first; fewer are clearer and cheaper to draw")

    plots = Plots(gui, tabs.add_tab("Plots", viser.Icon.CHART_LINE), ui)

    with tabs.add_tab("Data", viser.Icon.DATABASE):
        dataset = gui.add_text("Dataset", "", hint="a BOP dataset folder (root or split)")
        scene_id = gui.add_text("Scene id", "", hint="empty: the first scene")
        im_id = gui.add_text("Frame id", "", hint="empty: the first frame")
        load = gui.add_button("Load dataset", icon=viser.Icon.FOLDER_OPEN)
        demo = gui.add_button("Load demo", icon=viser.Icon.BOX, color="gray")
        sequence = build_sequence_tab(gui)
        # The colour image first, where the dataset has one: what poses are checked against by eye.
        rgb_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="colour image", format="jpeg",
                                  visible=False)
        depth_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="depth", format="png", visible=False)
        depth_legend = gui.add_html("")
        workers = gui.add_markdown("")

    with tabs.add_tab("Label", viser.Icon.PENCIL):
        label = build_label_tab(gui)
        # What the labels are checked against by eye, where the dataset has a colour image.
        label_rgb = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="colour image", format="jpeg",
                                  visible=False)

    with tabs.add_tab("Sessions", viser.Icon.DEVICE_FLOPPY):
        sessions = build_sessions_tab(gui)

    return Panel(
        title=title, error=error, field_style=field_style, status=status, busy=busy, busy_bar=busy_bar,
        view_legend=view_legend, camera=camera, visibility=visibility, truth=truth, step=step, run=run,
        pause=pause, reset=reset, method=method, particles=particles, iterations=iterations, sigma_xy=sigma_xy,
        sigma_z=sigma_z, sigma_angles=sigma_angles, likelihood=like, seed=seed, pending=pending,
        stop_on_convergence=stop, timings=timings, posterior=posterior, rank=rank, best=best, scene_mode=scene_mode,
        physics_change=physics_change, heatmap_mode=heatmap_mode, legend=legend, heat_image=heat_image,
        max_particles=max_particles, plots=plots, dataset=dataset, scene_id=scene_id, im_id=im_id, load=load,
        demo=demo, sequence=sequence, depth_image=depth_image, depth_legend=depth_legend, rgb_image=rgb_image,
        workers=workers, label=label, label_rgb=label_rgb, sessions=sessions,
    )


RESET_NOTE = ("<small>Method, particles, iterations and σ apply at the next step; **likelihood and seed apply at "
              "Reset**.</small>")


def pending_markdown(in_use: tuple[str, int], shown: tuple[str, int]) -> str:
    """The note under the settings: which typed settings wait for Reset (``in_use``/``shown``: likelihood, seed)."""
    waiting = [f"{name} {new}" for name, old, new in (("likelihood", in_use[0], shown[0]),
                                                       ("seed", in_use[1], shown[1])) if old != new]
    if not waiting:
        return RESET_NOTE
    return f"**⏳ {' and '.join(waiting)}: waiting for Reset** (the run uses {in_use[0]}, seed {in_use[1]})."
