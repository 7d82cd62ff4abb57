"""Scenes that share objects' poses, each shared pose drawn once.

Settling, the turns it tries and the posterior's sweep score batches in which each scene moves one object (or a
few) of a common scene and leaves the others where they are. A software renderer's cost follows the triangles it
draws, so drawing every scene's unmoved objects again is most of such a batch's cost. Here each scene draws only
its own objects, the objects it shares with the others are drawn once per batch (per set of objects shared), and
each pixel keeps the nearer of the two surfaces: what a z-buffer drawing them together keeps. On a frame of three
YCB-Video objects a scene of one object moved renders in about half the time (docs/journal/2026-11.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.render.depth import DepthRenderer
from workbench.render.likelihood import ImageTerms, LikelihoodConfig


def common_poses(T_world_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each object of the scenes ``T_world_obj`` (B, K, 4, 4), the pose that most of them give it (equal
    values) -> (those poses (K, 4, 4), which scenes have them (B, K) bool). An object that no two scenes give the
    same pose is shared by none (its column False)."""
    B, K = T_world_obj.shape[:2]
    common = np.array(T_world_obj[0], dtype=np.float64, copy=True)
    shared = np.zeros((B, K), dtype=bool)
    for k in range(K):
        poses, which, counts = np.unique(T_world_obj[:, k].reshape(B, 16), axis=0, return_inverse=True,
                                         return_counts=True)
        top = int(np.argmax(counts))  # the first (lowest) of equally common poses: the same choice every run
        if counts[top] >= 2:
            common[k] = poses[top].reshape(4, 4)
            shared[:, k] = which.ravel() == top
    return common, shared


def keep_nearer(own: np.ndarray, shared: np.ndarray) -> None:
    """Per pixel, the nearer of each depth image ``own`` (n, H, W) float32 and ``shared`` (H, W) float32 (0 =
    nothing drawn), into ``own``. Depths are positive, and positive float32 order as their bits do as unsigned
    integers: minus one, nothing drawn becomes the largest, so the nearer is the smaller, without a copy."""
    a, b = own.view(np.uint32), shared.view(np.uint32)
    a -= 1
    np.minimum(a, b - np.uint32(1), out=a)
    a += 1


@dataclass
class Drawn:
    """A batch drawn with its shared poses once (``draw_shared``): ``order`` (B,) the scenes sorted by ``groups``
    (G, K), which objects each group shares; ``starts`` (G + 1,) where each group's scenes begin in that order;
    ``own`` (B, H, W) each scene's own objects, in that order; ``shared`` (G, H, W) each group's shared objects."""

    order: np.ndarray
    groups: np.ndarray
    starts: np.ndarray
    own: np.ndarray
    shared: np.ndarray

    def group(self, g: int) -> slice:
        """Group ``g``'s scenes in ``order`` (and in ``own``)."""
        return slice(int(self.starts[g]), int(self.starts[g + 1]))


def draw_shared(renderer: DepthRenderer, T_world_obj: np.ndarray) -> Drawn:
    """The scenes ``T_world_obj`` (B, K, 4, 4) table frame drawn with the poses that several share
    (``common_poses``) once: each scene draws the objects it does not share, in tiles grouped by which objects
    those are (so that each object is drawn in a few runs of tiles), and one more tile per group draws the shared
    ones. Where nothing is shared (or one scene, or one object), one group of every scene drawn whole."""
    T_world_obj = np.asarray(T_world_obj, dtype=np.float64)
    B, K = T_world_obj.shape[:2]
    common, shared = common_poses(T_world_obj) if B >= 2 and K >= 2 else (None, np.zeros((B, K), dtype=bool))
    if not shared.any():
        depth = renderer.render(T_world_obj)
        return Drawn(np.arange(B), np.zeros((1, K), dtype=bool), np.array([0, B]), depth,
                     np.zeros((1, *depth.shape[1:]), dtype=depth.dtype))
    groups, group = np.unique(shared, axis=0, return_inverse=True)  # (G, K) which objects a group shares
    order = np.argsort(group.ravel(), kind="stable")
    scenes = np.concatenate([T_world_obj[order], np.repeat(common[None], len(groups), axis=0)])
    depth = renderer.render(scenes, np.concatenate([~shared[order], groups]))
    starts = np.searchsorted(group.ravel()[order], np.arange(len(groups) + 1))
    return Drawn(order, groups, starts, depth[:B], depth[B:])


def render_shared(renderer: DepthRenderer, T_world_obj: np.ndarray) -> np.ndarray:
    """``renderer.render(T_world_obj)`` (B, K, 4, 4) table frame -> (B, H, W) float32 camera-z depth, 0 = no object,
    drawn by ``draw_shared``: each scene keeps the nearer surface of its own tile and its group's
    (``keep_nearer``)."""
    drawn = draw_shared(renderer, T_world_obj)
    for g in np.flatnonzero(drawn.groups.any(axis=1)):
        keep_nearer(drawn.own[drawn.group(g)], drawn.shared[g])
    out = np.empty_like(drawn.own)
    out[drawn.order] = drawn.own
    return out


def drawn_loglik(drawn: Drawn, observed: np.ndarray, background: np.ndarray, config: LikelihoodConfig,
                 segments: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``scene_loglik`` of each scene of ``drawn`` -> (B,) float64, in the batch's order, and the part of it the
    clutter floor adds (B,) (``ImageTerms.scene``; zeros when the floor is off): each group's shared tile scored
    whole, and each scene by how much its own objects change that (``ImageTerms.drawn_over``), which computes only
    their pixels. Equal to scoring ``render_shared``'s depth but for the order of the sums. A group that shares
    nothing (a batch of projected particles) is scored as ``scene_loglik`` scores its tiles, bit for bit.
    ``segments``: the clutter pieces, as ``scene_loglik``."""
    out, floor = np.empty(len(drawn.order)), np.empty(len(drawn.order))
    terms = ImageTerms.of(observed, background, config, segments)
    shares = drawn.groups.any(axis=1)  # (G,)
    base, base_floor = np.zeros(len(shares)), np.zeros(len(shares))
    if shares.any():  # every sharing group's tile in one pass over the image's empty-table term
        plain, gain = terms.scene(drawn.shared[shares])
        base[shares], base_floor[shares] = plain + gain, gain
    for g in range(len(shares)):
        own = drawn.own[drawn.group(g)]
        if shares[g]:
            plain, gain = terms.drawn_over(drawn.shared[g], own)
            ll, gain = base[g] + (plain + gain), base_floor[g] + gain
        else:
            plain, gain = terms.scene(own)
            ll = plain + gain
        out[drawn.order[drawn.group(g)]] = ll
        floor[drawn.order[drawn.group(g)]] = gain
    return out, floor
