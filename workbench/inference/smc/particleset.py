"""Per-particle arrays kept together: one container, so that indexing, copying where a mask holds,
concatenation and (de)serialisation are written once.

``Rows`` is the shared behaviour: a dataclass whose fields named in ``ROWS`` are arrays with one row per particle
(first axis). ``ParticleSet`` is the filter's particle set; ``evaluation.Evaluation`` (a batch's results) is the
same kind of container with fewer rows. Like ``particles``' ``ThetaParticles``: every per-particle array lives here,
so that resampling or a Metropolis-Hastings accept moves all of them at once and none is forgotten.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import ClassVar, Self

import numpy as np


class Rows:
    """Mixin for dataclasses whose ``ROWS`` fields are per-particle arrays of equal length (first axis)."""

    ROWS: ClassVar[tuple[str, ...]]

    def __len__(self) -> int:
        return len(getattr(self, self.ROWS[0]))

    def __getitem__(self, idx) -> Self:
        """The rows at ``idx`` (an index array, a mask or a slice), as copies; other fields kept."""
        return replace(self, **{name: np.array(getattr(self, name)[idx]) for name in self.ROWS})

    def copyto(self, src: Self, where: np.ndarray) -> None:
        """In place: row i becomes ``src``'s row i where ``where`` (N,) is true (an accepted Metropolis-Hastings
        move). ``src`` has the same length."""
        for name in self.ROWS:
            dst = getattr(self, name)
            np.copyto(dst, getattr(src, name), where=where.reshape((-1,) + (1,) * (dst.ndim - 1)))

    def put(self, at: np.ndarray, src: Self) -> None:
        """In place: rows ``at`` (M,) become ``src``'s rows (M rows)."""
        for name in self.ROWS:
            getattr(self, name)[at] = getattr(src, name)

    def copy(self) -> Self:
        return replace(self, **{name: getattr(self, name).copy() for name in self.ROWS})

    @classmethod
    def concatenate(cls, parts: list[Self]) -> Self:
        """The parts' rows one after another; other fields from ``merge_other``."""
        rows = {name: np.concatenate([getattr(p, name) for p in parts]) for name in cls.ROWS}
        return cls(**rows, **cls.merge_other(parts))

    @classmethod
    def interleave(cls, first: np.ndarray, a: Self, b: Self) -> Self:
        """The batch whose rows where ``first`` (B,) is true are ``a``'s, in order, and the others ``b``'s."""
        rows = {}
        for name in cls.ROWS:
            x, y = getattr(a, name), getattr(b, name)
            out = np.empty((len(first), *x.shape[1:]), dtype=np.result_type(x, y))
            out[first], out[~first] = x, y
            rows[name] = out
        return cls(**rows, **cls.merge_other([a, b]))

    @classmethod
    def merge_other(cls, parts: list[Self]) -> dict:
        """The fields that are not rows, for a batch made of ``parts`` (none by default)."""
        return {f.name: getattr(parts[0], f.name) for f in fields(cls) if f.name not in cls.ROWS}

    def arrays(self) -> dict[str, np.ndarray]:
        """The rows by name, as they are (for saving: ``np.savez``)."""
        return {name: getattr(self, name) for name in self.ROWS}


@dataclass
class ParticleSet(Rows):
    """The filter's N particles, table frame: ``hypotheses`` (N, K, 4, 4) as proposed, ``projected`` (N, K, 4, 4)
    after physics, ``loglik`` (N,) float64 (-inf where physics failed or a scene rests outside the object region),
    ``status`` (N,) int8 physics status, ``kinds`` (N,) int8 the ``MoveKind`` that produced each particle."""

    hypotheses: np.ndarray
    projected: np.ndarray
    loglik: np.ndarray
    status: np.ndarray
    kinds: np.ndarray

    ROWS: ClassVar[tuple[str, ...]] = ("hypotheses", "projected", "loglik", "status", "kinds")
    DTYPES: ClassVar[dict[str, str]] = {"hypotheses": "float64", "projected": "float64", "loglik": "float64",
                                        "status": "int8", "kinds": "int8"}

    @classmethod
    def evaluated(cls, hypotheses: np.ndarray, evaluation, kinds: np.ndarray) -> "ParticleSet":
        """Hypotheses (B, K, 4, 4) with their ``evaluation.Evaluation`` and move kinds (B,), as copies."""
        return cls(hypotheses.copy(), evaluation.projected.copy(), evaluation.loglik.copy(),
                   evaluation.status.copy(), np.asarray(kinds, np.int8).copy())

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> "ParticleSet":
        """The inverse of ``arrays()``, as copies in the set's dtypes."""
        return cls(**{name: np.array(arrays[name], dtype=cls.DTYPES[name]) for name in cls.ROWS})
