"""The settings of ``workbench label``."""

from __future__ import annotations

from dataclasses import dataclass, field

from workbench.errors import InputError
from workbench.inference.config import EstimatorConfig
from workbench.label.check import CheckConfig

MAX_FIT_FRAMES = 1000  # each frame summed costs a renderer and a render per scene scored


@dataclass(frozen=True)
class LabelConfig:
    """``fit_frames``: how many frames, spread over the sequence, the multi-view fit sums (0: no fit, the first
    frame's answer carried as it is); ``snap``: physics puts the fitted labels at rest, and the depth fits them again
    within ``settle_shift`` and ``settle_turn`` of the rest (off: see ``run.fitted_labels``); ``check``: the per-frame
    check; ``ends``: object id -> the last frame of its label (an object taken out)."""

    fit_frames: int = 10
    snap: bool = False
    check: CheckConfig = CheckConfig()
    ends: dict[int, int] = field(default_factory=dict)
    settle_shift: float = EstimatorConfig.settle_shift  # metres: the fit after physics, as the estimator's settling
    settle_turn: float = EstimatorConfig.settle_turn  # degrees

    def validate(self) -> None:
        if not 0 <= self.fit_frames <= MAX_FIT_FRAMES:
            raise InputError("--fit-frames", f"must lie in [0, {MAX_FIT_FRAMES}], got {self.fit_frames}")
        self.check.validate()
