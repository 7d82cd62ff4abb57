"""Scenes that share objects' poses, each shared pose drawn once.

Settling, the turns it tries and the posterior's sweep score batches in which each scene moves one object (or a
few) of a common scene and leaves the others where they are. A software renderer's cost follows the triangles it
draws, so drawing every scene's unmoved objects again is most of such a batch's cost. Here each scene draws only
its own objects, the objects it shares with the others are drawn once per batch (per set of objects shared), and
each pixel keeps the nearer of the two surfaces: what a z-buffer drawing them together keeps. On a frame of three
YCB-Video objects a scene of one object moved renders in about half the time (docs/benchmarks.md).
"""

from __future__ import annotations

import numpy as np

from workbench.render.depth import DepthRenderer


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


def render_shared(renderer: DepthRenderer, T_world_obj: np.ndarray) -> np.ndarray:
    """``renderer.render(T_world_obj)`` (B, K, 4, 4) table frame -> (B, H, W) float32 camera-z depth, 0 = no object,
    drawing the poses that several scenes share (``common_poses``) once: each scene draws the objects it does not
    share, in tiles grouped by which objects those are (so that each object is drawn in a few runs of tiles), one
    more tile per group draws the shared ones, and each scene keeps the nearer surface of its tile and its group's
    (``keep_nearer``)."""
    T_world_obj = np.asarray(T_world_obj, dtype=np.float64)
    B, K = T_world_obj.shape[:2]
    if B < 2 or K < 2:
        return renderer.render(T_world_obj)
    common, shared = common_poses(T_world_obj)
    if not shared.any():
        return renderer.render(T_world_obj)
    groups, group = np.unique(shared, axis=0, return_inverse=True)  # (G, K) which objects a group shares
    order = np.argsort(group.ravel(), kind="stable")
    scenes = np.concatenate([T_world_obj[order], np.repeat(common[None], len(groups), axis=0)])
    depth = renderer.render(scenes, np.concatenate([~shared[order], groups]))
    starts = np.searchsorted(group.ravel()[order], np.arange(len(groups) + 1))
    for g in range(len(groups)):  # each group's scenes are consecutive in ``order``
        keep_nearer(depth[starts[g]:starts[g + 1]], depth[B + g])
    out = np.empty((B, *depth.shape[1:]), dtype=depth.dtype)
    out[order] = depth[:B]
    return out
