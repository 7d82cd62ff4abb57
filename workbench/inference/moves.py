"""The move kinds, the mix the default search draws them from, and what each contributes.

Each particle of an iteration takes one move kind, drawn from ``MoveMix``; the kind of the move that produced
each particle travels with it (``Estimator.kinds``), so the per-kind counts say how many of each were proposed,
how many survived resampling (PI-PF) or were accepted (PI-MCPF), and which produced the estimate.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from enum import IntEnum
from typing import Literal

import numpy as np

from workbench.errors import InputError

Proposals = Literal["default", "paper"]
PROPOSALS: tuple[str, ...] = ("default", "paper")


class MoveKind(IntEnum):
    START = 0  # a random start (iteration 0)
    DATA_START = 1  # a data-driven start (iteration 0)
    JOINT = 2  # Gaussian step of every object (the paper's diffusion)
    SINGLE = 3  # Gaussian step of one object
    FACE = 4  # one object onto another resting face
    TURN = 5  # one object turned by 90/180/270 degrees
    STACK = 6  # one object onto another object, or off it
    DATA = 7  # one object to a data-driven candidate
    ICP = 8  # one object refined by ICP
    RELOCATE = 9  # one object to a random place in the object region, dropped onto whatever is below
    POLISH = 10  # the estimate with one object on a candidate, or two objects' places exchanged (polish.py)
    ASSEMBLE = 11  # every object on a candidate, the joint assignment that explains the depth best (assemble.py)
    BASE = 12  # the estimate with a base put under a top it or a candidate shows (polish.stacked)

    @property
    def label(self) -> str:
        return self.name.lower().replace("_", " ")


@dataclass(frozen=True)
class MoveMix:
    """Probabilities of each move kind per particle and iteration (normalised when used). ``paper()``: joint
    Gaussian diffusion only, as Desingh et al. define PI-PF and PI-MCPF."""

    joint: float = 0.25
    single: float = 0.30
    face: float = 0.05
    turn: float = 0.06
    stack: float = 0.04
    data: float = 0.15
    icp: float = 0.10
    relocate: float = 0.05

    @staticmethod
    def paper() -> "MoveMix":
        return MoveMix(joint=1.0, single=0.0, face=0.0, turn=0.0, stack=0.0, data=0.0, icp=0.0, relocate=0.0)

    def validate(self) -> None:
        p = self.as_array()
        if not np.all(np.isfinite(p)) or np.any(p < 0) or p.sum() <= 0:
            raise InputError("moves", f"move probabilities must be >= 0 with a positive sum, got {self}")

    def as_array(self) -> np.ndarray:
        """(8,) probabilities in field order (unnormalised)."""
        return np.array([getattr(self, f.name) for f in fields(self)], dtype=np.float64)

    def kinds(self) -> np.ndarray:
        """(8,) the MoveKind of each field, in field order: each field is named after its kind."""
        return np.array([int(MoveKind[f.name.upper()]) for f in fields(self)])

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """One move kind per particle -> (n,) int8 MoveKind values."""
        p = self.as_array()
        return self.kinds()[rng.choice(len(p), size=n, p=p / p.sum())].astype(np.int8)
