"""The registry of move kinds, the mix the default search draws them from, and the kinds' codes.

Each particle of an iteration takes one move kind, drawn from ``MoveMix``; the kind of the move that produced
each particle travels with it (``ParticleSet.kinds``), so the per-kind counts say how many of each were proposed,
how many survived resampling (PI-PF) or were accepted (PI-MCPF), and which produced the estimate.

Adding a kind: a module with a ``context.Move`` subclass (its name, code, default share and ``propose``), and one
line in ``MOVES``. ``MoveKind``, the mix's defaults, its validation and the counts all follow from ``MOVES``.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import IntEnum
from typing import Literal

import numpy as np

from workbench.errors import InputError
from workbench.inference.search.moves import kinds
from workbench.inference.search.moves.context import Move

Proposals = Literal["default", "paper"]
PROPOSALS: tuple[str, ...] = ("default", "paper")

# The moves drawn per particle and iteration, in the mix's order (the order the random draws use).
MOVES: tuple[Move, ...] = (
    kinds.Joint(),
    kinds.Single(),
    kinds.Face(),
    kinds.Turn(),
    kinds.Stack(),
    kinds.Data(),
    kinds.Icp(),
    kinds.Relocate(),
)

# Where a particle comes from when not from a drawn move. Codes are stored with the particles (sessions keep
# them): never renumber.
OTHER_KINDS = {
    "START": 0,  # a random start (iteration 0)
    "DATA_START": 1,  # a data-driven start (iteration 0)
    "POLISH": 10,  # the estimate with one object on a candidate, or two objects' places exchanged (polish.py)
    "ASSEMBLE": 11,  # every object on a candidate, the joint assignment that explains the depth best (assemble.py)
    "BASE": 12,  # the estimate with a base put under a top it or a candidate shows (polish.stacked)
}


class _Kind(IntEnum):
    @property
    def label(self) -> str:
        return self.name.lower().replace("_", " ")


# Every kind by its code: the other kinds and each registered move's (e.g. MoveKind.JOINT == 2).
MoveKind = _Kind("MoveKind", {**OTHER_KINDS, **{m.name.upper(): m.code for m in MOVES}})
if len(MoveKind) != len(OTHER_KINDS) + len(MOVES):
    raise RuntimeError("two move kinds share a code or a name: every Move needs its own")
REGISTRY: dict[int, Move] = {m.code: m for m in MOVES}


class MoveMix:
    """Shares of each registered move kind per particle and iteration (normalised when drawn); immutable.
    ``MoveMix()`` holds each move's default share, ``MoveMix(joint=1.0, single=0.0)`` overrides some,
    ``paper()``: joint Gaussian diffusion only, as Desingh et al. define PI-PF and PI-MCPF."""

    def __init__(self, **shares: float):
        unknown = sorted(set(shares) - {m.name for m in MOVES})
        if unknown:
            raise InputError("moves", f"unknown move kinds {unknown}; the kinds are {[m.name for m in MOVES]}")
        self._shares = tuple((m.name, float(shares.get(m.name, m.share))) for m in MOVES)

    @staticmethod
    def paper() -> "MoveMix":
        return MoveMix(**{m.name: float(m.name == "joint") for m in MOVES})

    @staticmethod
    def from_dict(shares: Mapping[str, float]) -> "MoveMix":
        """A saved mix (``as_dict``): a kind it does not name gets share 0, as it ran without it."""
        return MoveMix(**{**{m.name: 0.0 for m in MOVES}, **shares})

    def as_dict(self) -> dict[str, float]:
        return dict(self._shares)

    def replace(self, **shares: float) -> "MoveMix":
        return MoveMix(**{**self.as_dict(), **shares})

    def for_state(self, state: str) -> "MoveMix":
        """The mix for the particle state: in the reduced (x, y, z, yaw) the kinds that tilt an object get 0."""
        return self if state == "6dof" else self.replace(**{m.name: 0.0 for m in MOVES if m.tilts})

    def validate(self) -> None:
        p = self.as_array()
        if not np.all(np.isfinite(p)) or np.any(p < 0) or p.sum() <= 0:
            raise InputError("moves", f"move probabilities must be >= 0 with a positive sum, got {self}")

    def as_array(self) -> np.ndarray:
        """(M,) shares in ``MOVES`` order (unnormalised)."""
        return np.array([s for _, s in self._shares], dtype=np.float64)

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """One move kind per particle -> (n,) int8 MoveKind values."""
        p = self.as_array()
        codes = np.array([m.code for m in MOVES])
        return codes[rng.choice(len(p), size=n, p=p / p.sum())].astype(np.int8)

    def __eq__(self, other) -> bool:
        return isinstance(other, MoveMix) and self._shares == other._shares

    def __hash__(self) -> int:
        return hash(self._shares)

    def __repr__(self) -> str:
        return "MoveMix(" + ", ".join(f"{n}={s:g}" for n, s in self._shares) + ")"
