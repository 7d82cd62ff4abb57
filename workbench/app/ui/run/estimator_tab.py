"""The Estimator tab's controls (``EstimatorTab``): what they show and what they read back. ``settings.SettingsForm``
gives them their behaviour."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import viser

from workbench.app.ui.widgets.numeric import NumberRule, parse_list
from workbench.errors import InputError
from workbench.inference.config import MAX_BUDGET_S, MAX_SIGMA_M, EstimatorConfig
from workbench.inference.smc.particles import Sigma

METHOD_LABELS = {"PI-PF": "pipf", "PI-MCPF": "mcpf"}
LIKELIHOODS = ("robust", "ssd")
SIGMA_XY, SIGMA_Z, SIGMA_ANGLES = "σ x, y (cm)", "σ elevation (cm)", "σ roll, pitch, yaw (°)"
# Every typed number is read by the one rule (``numeric``); a diffusion beyond these leaves any table scene
# (EstimatorConfig's MAX_SIGMA_M, MAX_SIGMA_RAD).
PARTICLES = NumberRule("Particles", 1, 100_000, whole=True)
ITERATIONS = NumberRule("Iterations", 0, 100_000, whole=True)
SEED = NumberRule("Seed", 0, 2**32 - 1, whole=True)
BUDGET = NumberRule("Budget (s)", 0.1, MAX_BUDGET_S, "s")
SIGMA_XY_RULES = (NumberRule("x", 0, MAX_SIGMA_M * 100, "cm"), NumberRule("y", 0, MAX_SIGMA_M * 100, "cm"))
SIGMA_Z_RULE = NumberRule(SIGMA_Z, 0, MAX_SIGMA_M * 100, "cm")
SIGMA_ANGLE_RULES = tuple(NumberRule(a, 0, 360, "°") for a in ("roll", "pitch", "yaw"))
RESET_NOTE = ("<small>Method, particles, iterations and σ apply at the next step, the budget at the next Run; "
              "**likelihood and seed apply at Reset**.</small>")


@dataclass
class EstimatorTab:
    method: viser.GuiDropdownHandle
    # Text, not number inputs: a number input silently empties itself on "abc" and keeps the old value unseen.
    particles: viser.GuiTextHandle
    iterations: viser.GuiTextHandle
    budget: viser.GuiTextHandle  # seconds; empty: until converged
    sigma_xy: viser.GuiTextHandle  # "x, y" in cm
    sigma_z: viser.GuiTextHandle
    sigma_angles: viser.GuiTextHandle  # "roll, pitch, yaw" in degrees
    likelihood: viser.GuiDropdownHandle
    seed: viser.GuiTextHandle
    pending: viser.GuiMarkdownHandle  # what applies at Reset, and what is waiting for it
    stop_on_convergence: viser.GuiCheckboxHandle
    timings: viser.GuiMarkdownHandle

    @property
    def fields(self) -> dict[str, viser.GuiTextHandle]:
        """The typed fields by their labels (the names errors are reported under)."""
        return {"Particles": self.particles, "Iterations": self.iterations, BUDGET.label: self.budget,
                SIGMA_XY: self.sigma_xy,
                SIGMA_Z: self.sigma_z, SIGMA_ANGLES: self.sigma_angles, "Seed": self.seed}

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
        labels = {id(h): label for label, h in self.fields.items()}

        def read(handle, parse, fallback):
            try:
                return parse(handle.value)
            except InputError as err:
                errors[labels.get(id(handle), str(err.path))] = err.problem
                return fallback

        # A sigma shown as it was set (to the 6 digits shown) keeps base's exact value: cm and degrees do not
        # round-trip to the last bit, and a restored session must step with exactly its saved sigma.
        def exact(shown, value, scale):
            return value if abs(shown - value * scale) <= 1e-6 * abs(value * scale) + 1e-12 else shown / scale

        sx, sy = read(self.sigma_xy, lambda t: parse_list(t, SIGMA_XY_RULES, SIGMA_XY), (s.x * 100, s.y * 100))
        sz = read(self.sigma_z, SIGMA_Z_RULE.parse, s.z * 100)
        roll, pitch, yaw = read(self.sigma_angles, lambda t: parse_list(t, SIGMA_ANGLE_RULES, SIGMA_ANGLES),
                                (s.roll * deg, s.pitch * deg, s.yaw * deg))
        config = replace(
            base,
            method=METHOD_LABELS[self.method.value],
            particles=read(self.particles, PARTICLES.parse, base.particles),
            iterations=read(self.iterations, ITERATIONS.parse, base.iterations),
            budget_s=read(self.budget, parse_budget, base.budget_s),
            sigma=Sigma(x=exact(sx, s.x, 100.0), y=exact(sy, s.y, 100.0), z=exact(sz, s.z, 100.0),
                        roll=exact(roll, s.roll, deg), pitch=exact(pitch, s.pitch, deg), yaw=exact(yaw, s.yaw, deg)),
            seed=read(self.seed, SEED.parse, base.seed),
        )
        config.validate()
        return config, errors

    def revert(self, labels, config: EstimatorConfig) -> None:
        """Put ``config``'s values back into the fields labelled ``labels`` (call inside ``Quiet``)."""
        s, deg = config.sigma, 180.0 / np.pi
        values = {
            "Particles": (self.particles, str(config.particles)),
            "Iterations": (self.iterations, str(config.iterations)),
            BUDGET.label: (self.budget, shown_budget(config.budget_s)),
            SIGMA_XY: (self.sigma_xy, shown_numbers(s.x * 100, s.y * 100)),
            SIGMA_Z: (self.sigma_z, shown_numbers(s.z * 100)),
            SIGMA_ANGLES: (self.sigma_angles, shown_numbers(s.roll * deg, s.pitch * deg, s.yaw * deg)),
            "Seed": (self.seed, str(config.seed)),
        }
        for label in labels:
            if label in values:
                handle, text = values[label]
                handle.value = text

    @property
    def field_ids(self) -> dict[str, str]:
        """The typed fields' element ids by their labels (``Reporter.field_errors`` outlines them by these)."""
        return {label: h._impl.uuid for label, h in self.fields.items()}

    def show_config(self, config: EstimatorConfig, likelihood: str) -> None:
        """Put ``config`` into the controls (call inside ``Quiet``: these writes fire the controls' callbacks)."""
        self.method.value = {v: k for k, v in METHOD_LABELS.items()}[config.method]
        self.revert(("Particles", "Iterations", BUDGET.label, SIGMA_XY, SIGMA_Z, SIGMA_ANGLES, "Seed"), config)
        self.likelihood.value = likelihood


def shown_numbers(*values: float) -> str:
    return ", ".join(f"{v:.6g}" for v in values)


def parse_budget(text: object) -> float | None:
    """The Budget field: empty (or "none") for a run until converged, else seconds by the one rule."""
    return None if str(text).strip().lower() in ("", "none") else BUDGET.parse(text)


def shown_budget(budget_s: float | None) -> str:
    return "" if budget_s is None else shown_numbers(budget_s)



def build_estimator_tab(gui: viser.GuiApi, config: EstimatorConfig, likelihood: str) -> EstimatorTab:
    """The tab's controls showing ``config`` and ``likelihood`` (call inside the tab)."""
    method = gui.add_dropdown("Method", tuple(METHOD_LABELS),
                              initial_value={v: k for k, v in METHOD_LABELS.items()}[config.method],
                              hint="applies at the next step")
    particles = gui.add_text("Particles", str(config.particles), hint="1 to 100000; applies at the next step")
    iterations = gui.add_text("Iterations", str(config.iterations), hint="the most a Run steps")
    budget = gui.add_text(BUDGET.label, shown_budget(config.budget_s),
                          hint="anytime: a Run stops by this many seconds and answers with its best scene so far; "
                               "empty: until converged or the iterations end")
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
    return EstimatorTab(method=method, particles=particles, iterations=iterations, budget=budget, sigma_xy=sigma_xy,
                        sigma_z=sigma_z, sigma_angles=sigma_angles, likelihood=like, seed=seed, pending=pending,
                        stop_on_convergence=stop, timings=timings)


def pending_markdown(in_use: tuple[str, int], shown: tuple[str, int]) -> str:
    """The note under the settings: which typed settings wait for Reset (``in_use``/``shown``: likelihood, seed)."""
    waiting = [f"{name} {new}" for name, old, new in (("likelihood", in_use[0], shown[0]),
                                                       ("seed", in_use[1], shown[1])) if old != new]
    if not waiting:
        return RESET_NOTE
    return f"**{' and '.join(waiting)}: waiting for Reset** (the run uses {in_use[0]}, seed {in_use[1]})."
