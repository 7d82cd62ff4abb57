"""Starts for flat objects from their outline: each thin resting face's footprint aligned in 2-D with a cluster's
points seen from above.

A thin object lying flat (scissors, a clamp, a marker) shows the sensor little but its top: a flat patch whose only
hint of heading and position is its outline. ICP cannot use an outline (point-to-plane matching on a flat top
leaves the object free to slide and turn in the plane), so its starts must already be right within a few
millimetres and degrees. Turned over, the same object shows its outline mirrored, 180 degrees and centimetres
away from any start on the other face. Here the footprint of each thin face is rasterised on a grid of
``CELL`` and correlated, in ``TURNS`` headings, with where the cluster has points at the object's height (a
gain) and where the sensor sees bare table (a loss): the best alignments of every face are the starts.
"""

from __future__ import annotations

import numpy as np
from scipy import fft, ndimage

from workbench.geometry import make_pose, rot_z
from workbench.inference.search.moves.resting import RestingPoses, height
from workbench.inference.search.scenepoints import (
    TABLE_CELL,
    ModelSamples,
    ScenePoints,
    table_cells,
)

CELL = TABLE_CELL  # m; the grid the footprints are aligned on (that of ``ScenePoints.table``)
TURNS = 72  # headings tried per face, 5 degrees apart
THIN = 0.04  # m; a face at most this tall ...
THIN_RATIO = 3.0  # ... whose footprint is at least this many times longer than it is tall is thin
PER_FACE = 2  # starts kept per face: the two best distinct alignments
# Thin faces aligned, the likeliest first: two for a flat object (either side up); a marker's four sides (a near
# cylinder's) show one outline, not worth aligning four times.
MAX_FACES = 2
BAND = 0.01  # m; cluster points up to this much above the face's height may be its top
MIN_POINTS = 30  # such points a cluster needs to place an outline (generated scissors' clusters: 138-291)
TABLE_LOSS = 1.0  # per footprint cell on bare table, against 1 per cell on the cluster's points
DISTINCT_M = 0.02  # m; alignments closer than this and DISTINCT_TURN are the same
DISTINCT_TURN = np.radians(20.0)


def thin_faces(rest: RestingPoses, hull: np.ndarray) -> list[int]:
    """The resting faces (indices into ``rest.rotations``) on which the object with convex-hull vertices ``hull``
    (V, 3) lies flat: at most THIN tall, and its horizontal extent at least THIN_RATIO times that; the MAX_FACES
    likeliest (``rest.probs``). None of a box's: its outline is a rectangle, whose heading the cluster's
    minimum-area rectangle and ICP on its sides give, and turned over it is the same rectangle (the generated
    flat boxes' outlines, aligned, crowded their libraries: `four` lost 2-3 of 16 objects at two seeds)."""
    if rest.box:
        return []
    out = []
    for f, R in enumerate(rest.rotations):
        xy = hull @ R[:2].T
        h = height(R, hull)
        if h <= THIN and float(np.max(np.ptp(xy, axis=0))) >= THIN_RATIO * h:
            out.append(f)
    return sorted(out, key=lambda f: -rest.probs[f])[:MAX_FACES]


def footprint(samples: ModelSamples, R: np.ndarray, lift: float, h: float) -> np.ndarray:
    """The xy (M, 2) m of the object's upper surface samples (those above 30 % of its height ``h``), resting with
    rotation R (3, 3) and its origin ``lift`` m above the table: what a sensor above it sees."""
    p = samples.points @ R.T
    return p[p[:, 2] + lift > 0.3 * h, :2]


def raster(cells: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A (H, W) float grid, 1 at each of the integer ``cells`` (N, 2) that lies inside it."""
    ok = np.all((cells >= 0) & (cells < np.array(shape)), axis=1)
    grid = np.zeros(shape)
    grid[cells[ok, 0], cells[ok, 1]] = 1.0
    return grid


def footprint_starts(cluster: np.ndarray, cloud: ScenePoints, rest: RestingPoses, samples: ModelSamples,
                     hull: np.ndarray, reach: float) -> list[np.ndarray]:
    """Poses (4, 4) of the object lying on each thin face on the table at the best PER_FACE distinct alignments
    of its footprint with the ``cluster`` (P, 3) (table frame, m): the footprint's cells on the cluster's points
    no higher than the face's height plus BAND, less TABLE_LOSS per cell on bare table (``cloud.table``, and no
    point above the table there). ``reach``: m, the object's horizontal reach from its origin."""
    faces = {f: height(rest.rotations[f], hull) for f in thin_faces(rest, hull)}  # face -> its height, m
    if np.count_nonzero(cluster[:, 2] <= max(faces.values(), default=0.0) + BAND) < MIN_POINTS:
        return []
    lo = table_cells(cluster[:, :2].min(axis=0) - reach)
    hi = table_cells(cluster[:, :2].max(axis=0) + reach)
    shape = tuple(int(n) for n in hi - lo + 1)
    near = cloud.points[np.all((cloud.points[:, :2] >= lo * CELL) & (cloud.points[:, :2] < (hi + 1) * CELL), axis=1)]
    bare = raster(cloud.table - lo, shape) * (1.0 - raster(table_cells(near[:, :2]) - lo, shape))
    m = int(np.ceil(reach / CELL)) + 1  # the footprint's grid: (2m + 1) cells a side, the origin in cell m
    out = []
    for f, h in faces.items():
        gain = raster(table_cells(cluster[cluster[:, 2] <= h + BAND, :2]) - lo, shape) - TABLE_LOSS * bare
        xy = footprint(samples, rest.rotations[f], float(rest.heights[f]), h)
        kernels = np.stack([ndimage.binary_closing(  # sparse samples leave holes between them
            raster(table_cells(xy @ rot_z(2 * np.pi * i / TURNS)[:2, :2].T) + m, (2 * m + 1, 2 * m + 1)))
            for i in range(TURNS)]).astype(np.float32)  # single precision: counts of a few hundred cells
        # Correlation as convolution with the flipped kernels, all headings in one batched FFT; cropped to 'same':
        # score[i, j] sums gain over footprint i with its cell m on cell j, the origin at (lo + j) CELL.
        size = tuple(fft.next_fast_len(n + 2 * m, real=True) for n in shape)
        spectrum = fft.rfft2(gain.astype(np.float32), size)[None] * fft.rfft2(kernels[:, ::-1, ::-1], size)
        full = fft.irfft2(spectrum, size)
        score = full[:, m:m + shape[0], m:m + shape[1]]
        best = []
        for i in range(TURNS):
            j = np.unravel_index(int(np.argmax(score[i])), shape)
            best.append((float(score[i][j]), 2 * np.pi * i / TURNS, (lo + np.array(j)) * CELL))
        kept: list[tuple[float, float, np.ndarray]] = []
        for s, turn, t in sorted(best, key=lambda b: -b[0]):
            if all(np.linalg.norm(t - u) > DISTINCT_M or abs((turn - v + np.pi) % (2 * np.pi) - np.pi) > DISTINCT_TURN
                   for _, v, u in kept):
                kept.append((s, turn, t))
            if len(kept) == PER_FACE:
                break
        out += [make_pose(rot_z(turn) @ rest.rotations[f], np.array([t[0], t[1], rest.heights[f]]))
                for _, turn, t in kept]
    return out
