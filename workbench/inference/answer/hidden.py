"""Where a hidden object can be: the places about its estimate where the camera would not see it either.

An object the sensor sees none of (``scenepoints.unseen``: every camera-facing sample of it lies behind what the
sensor sees, or out of view) scores the same wherever it stays out of sight: the likelihood is flat over a
region of the table, and the estimate is one place of that region, chosen by the search's priors, not by the depth.
Its modes (turns and faces at that one place) say nothing of the region. So the posterior also reports the region:
the object moved level, on a grid of ``SPACING`` out to ``REACH`` about its estimate, scored as given, the places
that put it inside another object dropped (``assemble.inside_share``), and the places whose scene scores within the
open gap of the estimate's kept. Each place's probability is its odds as the modes' are (``posterior.probabilities``),
normalised over the region. The object's modes are all at the estimate's place, so the chance that it is
elsewhere than them is the chance that the truth does not lie within the right-pose tolerance of that place
(``HidingRegion.estimate_share``).

The grid's spacing keeps every point of the region within 2 cm (the right-pose tolerance) of a place: half its
diagonal is 1.8 cm. A place is where the object's origin is; its heading is left open (the depth sees none of it).
Physics is not asked: a place keeps the estimate's height and face, on whatever held it there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.inference.answer.assemble import inside_share
from workbench.inference.search.geometry import Solid
from workbench.score.metrics import RIGHT_CM

SPACING = 0.025  # m between neighbouring places
REACH = 0.25  # m: the farthest place from the estimate's
# A place holds the probability of its grid cell (SPACING squared of table); the estimate is right where the truth
# lies within the right-pose tolerance of it, a disc of about twice that area.
TOLERANCE_CELLS = np.pi * (RIGHT_CM / 100.0) ** 2 / SPACING ** 2


@dataclass(frozen=True)
class HidingRegion:
    """Where a hidden object can be: ``places`` (P, 3) m, table frame, its origin at each (the estimate's first),
    with ``probabilities`` (P,) summing to 1, from their scenes' log-likelihood ``gaps`` (P,) to the estimate's."""

    places: np.ndarray
    probabilities: np.ndarray
    gaps: np.ndarray

    @property
    def estimate_share(self) -> float:
        """``estimate_share`` of the estimate's place: the chance that the truth lies within 2 cm of it."""
        return estimate_share(self.probabilities)

    @property
    def extent_m(self) -> float:
        """The largest distance (m) between two places: how far apart the object's possible places lie."""
        d = self.places[:, None, :2] - self.places[None, :, :2]
        return float(np.sqrt((d ** 2).sum(axis=-1)).max())


def estimate_share(probabilities: np.ndarray) -> float:
    """The chance that the truth lies within the right-pose tolerance (``metrics.RIGHT_CM``) of the estimate's
    place, from the region's place ``probabilities`` (P,), the estimate's first: its place's probability times the
    tolerance disc's area in grid cells (``TOLERANCE_CELLS``), at most 1. The estimate's modes share it."""
    return min(1.0, float(probabilities[0]) * TOLERANCE_CELLS)


def level_offsets(spacing: float = SPACING, reach: float = REACH) -> np.ndarray:
    """The grid's offsets (G, 2) m in the table plane, within ``reach`` of the origin, the origin first."""
    n = int(np.floor(reach / spacing))
    a = np.arange(-n, n + 1) * spacing
    grid = np.stack(np.meshgrid(a, a, indexing="ij"), axis=-1).reshape(-1, 2)
    grid = grid[np.linalg.norm(grid, axis=1) <= reach + 1e-9]
    return grid[np.argsort(np.linalg.norm(grid, axis=1), kind="stable")]


def free_places(scene: np.ndarray, k: int, offsets: np.ndarray, solids: list[Solid]) -> np.ndarray:
    """Object k of ``scene`` (K, 4, 4), table frame, moved level by each of ``offsets`` (G, 2) m -> (G,) bool:
    whether it there stays out of every other object (no core point of either inside the other's hull)."""
    moved = np.repeat(scene[k][None], len(offsets), axis=0)
    moved[:, :2, 3] += offsets
    free = np.ones(len(offsets), dtype=bool)
    for j in range(len(scene)):
        if j == k:
            continue
        other = np.repeat(scene[j][None], len(offsets), axis=0)
        near = np.linalg.norm(moved[:, :3, 3] - scene[j, :3, 3], axis=-1) < solids[k].radius + solids[j].radius
        if near.any():
            clash = ((inside_share(moved[near], solids[k], other[near], solids[j]) > 0)
                     | (inside_share(other[near], solids[j], moved[near], solids[k]) > 0))
            free[np.flatnonzero(near)[clash]] = False
    return free


def hiding_places(scene: np.ndarray, k: int, loglik: float, score, solids: list[Solid], open_gap: float,
                  offsets: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """The places where object k of ``scene`` (K, 4, 4), which the sensor does not see, can be as well: the level
    grid about it (``level_offsets``; or ``offsets`` (G, 2) m, the origin first: a region carried from an earlier
    view) out of the other objects (``free_places``), scored as given (``score``: scenes (N, K, 4, 4) ->
    log-likelihoods (N,)), those within ``open_gap`` log-units of ``loglik`` (the scene's) -> (places (P, 3) m, table
    frame, the estimate's first; their gaps (P,) to ``loglik``; scenes scored)."""
    offsets = level_offsets() if offsets is None else np.asarray(offsets, dtype=np.float64)
    free = free_places(scene, k, offsets, solids)
    free[0] = True  # the estimate's own place, wherever physics put it
    offsets = offsets[free]
    scenes = np.repeat(scene[None], len(offsets), axis=0)
    scenes[:, k, :2, 3] += offsets
    gaps = np.concatenate([[0.0], np.asarray(score(scenes[1:]), dtype=np.float64) - loglik]) if len(offsets) > 1 \
        else np.zeros(1)
    keep = gaps > -open_gap
    return scenes[keep, k, :3, 3].copy(), gaps[keep], len(offsets) - 1
