"""The control panel: every GUI handle of the workbench, built once on the server's shared GUI so that all
browser tabs see (and drive) the same run. Wiring the handles to actions is ``server.App``'s job."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import viser

from workbench.app.camera import FRAME_OBJECTS, FROM_SENSOR
from workbench.app.label_tab import LabelTab, build_label_tab
from workbench.app.particle_display import DEFAULT_DISPLAY
from workbench.app.plots import Plots
from workbench.app.sessions_panel import SessionsTab, build_sessions_tab
from workbench.app.views import HEATMAP_MODES, SCENE_MODES
from workbench.errors import InputError
from workbench.inference.config import EstimatorConfig
from workbench.inference.particles import Sigma

METHOD_LABELS = {"PI-PF": "pipf", "PI-MCPF": "mcpf"}
LIKELIHOODS = ("robust", "ssd")
DEFAULT_DRAWN = DEFAULT_DISPLAY


@dataclass
class Panel:
    title: viser.GuiMarkdownHandle
    error: viser.GuiMarkdownHandle
    status: viser.GuiMarkdownHandle
    view_legend: viser.GuiHtmlHandle
    camera: viser.GuiButtonGroupHandle
    step: viser.GuiButtonHandle
    run: viser.GuiButtonHandle
    pause: viser.GuiButtonHandle
    reset: viser.GuiButtonHandle
    # Estimator
    method: viser.GuiDropdownHandle
    particles: viser.GuiTextHandle  # text, not number: a number input silently empties itself on "abc"
    iterations: viser.GuiTextHandle
    sigma_xy: viser.GuiVector2Handle
    sigma_z: viser.GuiNumberHandle
    sigma_angles: viser.GuiVector3Handle
    likelihood: viser.GuiDropdownHandle
    seed: viser.GuiNumberHandle
    stop_on_convergence: viser.GuiCheckboxHandle
    timings: viser.GuiMarkdownHandle
    # Inspect
    rank: viser.GuiSliderHandle
    best: viser.GuiButtonHandle
    scene_mode: viser.GuiDropdownHandle
    physics_change: viser.GuiMarkdownHandle
    heatmap_mode: viser.GuiDropdownHandle
    legend: viser.GuiHtmlHandle
    heat_image: viser.GuiImageHandle
    show_observation: viser.GuiCheckboxHandle
    show_particles: viser.GuiCheckboxHandle
    show_best: viser.GuiCheckboxHandle
    show_gt: viser.GuiCheckboxHandle
    max_particles: viser.GuiNumberHandle
    # Plots
    plots: Plots
    # Data
    dataset: viser.GuiTextHandle
    scene_id: viser.GuiTextHandle
    im_id: viser.GuiTextHandle
    load: viser.GuiButtonHandle
    demo: viser.GuiButtonHandle
    depth_image: viser.GuiImageHandle
    depth_legend: viser.GuiHtmlHandle
    workers: viser.GuiMarkdownHandle
    # Label, Sessions
    label: LabelTab
    sessions: SessionsTab

    def estimator_config(self, base: EstimatorConfig) -> EstimatorConfig:
        """The controls' values over ``base`` (which keeps the settings the panel does not show)."""
        s = base.sigma
        check_sigmas(self.sigma_xy.value, self.sigma_z.value, self.sigma_angles.value)
        # A sigma shown as it was set keeps base's exact value: cm and degrees do not round-trip to the last bit,
        # and a restored session must step with exactly its saved sigma.
        exact = lambda shown, value, scale: value if shown == value * scale else shown / scale  # noqa: E731
        sx, sy = self.sigma_xy.value
        roll, pitch, yaw = self.sigma_angles.value
        deg = 180.0 / np.pi
        config = replace(
            base,
            method=METHOD_LABELS[self.method.value],
            particles=whole_number(self.particles.value, "Particles", 1, 100_000),
            iterations=whole_number(self.iterations.value, "Iterations", 0, 100_000),
            sigma=Sigma(x=exact(sx, s.x, 100.0), y=exact(sy, s.y, 100.0), z=exact(self.sigma_z.value, s.z, 100.0),
                        roll=exact(roll, s.roll, deg), pitch=exact(pitch, s.pitch, deg), yaw=exact(yaw, s.yaw, deg)),
            seed=int(self.seed.value),
        )
        config.validate()
        return config

    def show_config(self, config: EstimatorConfig, likelihood: str) -> None:
        """Put ``config`` into the controls (call inside ``Quiet``: these writes fire the controls' callbacks)."""
        s, deg = config.sigma, 180.0 / np.pi
        self.method.value = {v: k for k, v in METHOD_LABELS.items()}[config.method]
        self.particles.value = str(config.particles)
        self.iterations.value = str(config.iterations)
        self.sigma_xy.value = (s.x * 100.0, s.y * 100.0)
        self.sigma_z.value = s.z * 100.0
        self.sigma_angles.value = (s.roll * deg, s.pitch * deg, s.yaw * deg)
        self.seed.value = config.seed
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


def check_sigmas(xy_cm, z_cm, angles_deg) -> None:
    """The diffusion fields in the units they show (cm, degrees): each finite and >= 0."""
    for field, values, unit in (("σ x, y (cm)", xy_cm, "cm"), ("σ elevation (cm)", (z_cm,), "cm"),
                                ("σ roll, pitch, yaw (°)", angles_deg, "°")):
        for v in values:
            if not np.isfinite(v) or v < 0:
                shown = ", ".join(f"{float(x):g}" for x in values)
                raise InputError(field, f"each value must be a number >= 0 {unit}, got {shown}")


def build_panel(gui: viser.GuiApi, config: EstimatorConfig, likelihood: str) -> Panel:
    gui.configure_theme(control_width="large", dark_mode=False, show_logo=False, show_share_button=False)
    title = gui.add_markdown("**workbench** · nothing loaded")
    error = gui.add_markdown("", visible=False)
    status = gui.add_markdown("No iterations yet.")
    step = gui.add_button("Step", icon=viser.Icon.PLAYER_TRACK_NEXT, hint="one iteration")
    run = gui.add_button("Run", icon=viser.Icon.PLAYER_PLAY, color="green",
                         hint="iterate until the budget, convergence or Pause")
    pause = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE, disabled=True, hint="stop after this iteration")
    reset = gui.add_button("Reset", icon=viser.Icon.REFRESH, color="gray",
                           hint="new random particles (seed and likelihood model apply here)")
    # The 3D view's camera presets and its one legend, under the actions so that those stay at the top.
    with gui.add_folder("View", expand_by_default=True):
        camera = gui.add_button_group("Camera", (FRAME_OBJECTS, FROM_SENSOR))
        view_legend = gui.add_html("")
    tabs = gui.add_tab_group()

    with tabs.add_tab("Estimator", viser.Icon.ADJUSTMENTS):
        method = gui.add_dropdown("Method", tuple(METHOD_LABELS),
                                  initial_value={v: k for k, v in METHOD_LABELS.items()}[config.method])
        particles = gui.add_text("Particles", str(config.particles), hint="1 to 100000; takes effect at the next step")
        iterations = gui.add_text("Iterations", str(config.iterations), hint="the budget Run stops at")
        s = config.sigma
        sigma_xy = gui.add_vector2("σ x, y (cm)", (s.x * 100, s.y * 100), min=(0.0, 0.0), step=0.05,
                                   hint="diffusion of the position on the table")
        sigma_z = gui.add_number("σ elevation (cm)", s.z * 100, min=0.0, step=0.05)
        sigma_angles = gui.add_vector3(
            "σ roll, pitch, yaw (°)", tuple(float(a * (180.0 / np.pi)) for a in (s.roll, s.pitch, s.yaw)),
            min=(0.0, 0.0, 0.0), step=0.5,
        )
        like = gui.add_dropdown("Likelihood", LIKELIHOODS, initial_value=likelihood, hint="applies at Reset")
        seed = gui.add_number("Seed", config.seed, min=0, step=1, hint="applies at Reset")
        stop = gui.add_checkbox("Stop at convergence", True)
        timings = gui.add_markdown("")

    with tabs.add_tab("Inspect", viser.Icon.ZOOM_IN):
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
        show_observation = gui.add_checkbox("Observed points", True)
        show_particles = gui.add_checkbox("Particle cloud", True)
        show_best = gui.add_checkbox("Most likely scene", True)
        show_gt = gui.add_checkbox("Ground truth", False)
        max_particles = gui.add_number("Particles drawn", DEFAULT_DRAWN, min=1, max=20_000, step=1,
                                       hint="the most likely first; fewer are clearer and cheaper to draw")

    plots = Plots(gui, tabs.add_tab("Plots", viser.Icon.CHART_LINE))

    with tabs.add_tab("Data", viser.Icon.DATABASE):
        dataset = gui.add_text("Dataset", "", hint="a BOP dataset folder (root or split)")
        scene_id = gui.add_text("Scene id", "", hint="empty: the first scene")
        im_id = gui.add_text("Frame id", "", hint="empty: the first frame")
        load = gui.add_button("Load dataset", icon=viser.Icon.FOLDER_OPEN)
        demo = gui.add_button("Load demo", icon=viser.Icon.BOX, color="gray")
        depth_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="depth", format="png", visible=False)
        depth_legend = gui.add_html("")
        workers = gui.add_markdown("")

    with tabs.add_tab("Label", viser.Icon.PENCIL):
        label = build_label_tab(gui)

    with tabs.add_tab("Sessions", viser.Icon.DEVICE_FLOPPY):
        sessions = build_sessions_tab(gui)

    return Panel(
        title=title, error=error, status=status, view_legend=view_legend, camera=camera, step=step, run=run, pause=pause, reset=reset,
        method=method, particles=particles, iterations=iterations, sigma_xy=sigma_xy, sigma_z=sigma_z,
        sigma_angles=sigma_angles, likelihood=like, seed=seed, stop_on_convergence=stop, timings=timings,
        rank=rank, best=best, scene_mode=scene_mode, physics_change=physics_change, heatmap_mode=heatmap_mode,
        legend=legend, heat_image=heat_image, show_observation=show_observation, show_particles=show_particles,
        show_best=show_best, show_gt=show_gt, max_particles=max_particles, plots=plots,
        dataset=dataset, scene_id=scene_id, im_id=im_id, load=load, demo=demo, depth_image=depth_image,
        depth_legend=depth_legend, workers=workers, label=label, sessions=sessions,
    )
