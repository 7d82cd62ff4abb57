"""Data-driven placements: candidate poses fitted to clusters of observed points, and the starts and moves drawn
from them.

Each cluster of observed points above the table (those the current best scene does not explain) proposes places
for every object of fitting size: its position from the cluster (centroid, and a few spread points of a large
cluster, which may be several objects touching), its heading from the cluster's principal axes, its resting face
from the cluster's height. Each such start is fitted by ICP, slid along its horizontal axes where ICP cannot see a
slide (``slide``), and scored by how many observed points it explains, less the points it would hide (the sensor
sees through it). The best few per object form the ``Library``.

A move draws one object's pose from its library entries with a small Gaussian jitter: an independence proposal
whose density is a Gaussian mixture, so its log-q correction is exact.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

from workbench.evaluation import run_here
from workbench.geometry import (
    euler_to_matrix,
    make_pose,
    principal_heading,
    rot_z,
    rotation_angle,
)
from workbench.inference.search.footprint import footprint_starts
from workbench.inference.search.moves.proposal import Proposal, pick_objects
from workbench.inference.search.moves.resting import RestingPoses, height
from workbench.inference.search.refine import NEAR, STAGES, icp_batch, near
from workbench.inference.search.scenepoints import (
    EXPLAINED,
    SEEN_THROUGH,
    ModelSamples,
    ScenePoints,
)
from workbench.problem.problem import Problem

if TYPE_CHECKING:  # annotations only: the geometry module imports this one's neighbours
    from workbench.inference.search.geometry import SearchGeometry

JITTER_POS = 0.005  # m
JITTER_ANG = np.radians(3.0)
PER_OBJECT = 12  # candidates kept per object
# Clusters fitted per refit, largest first: at least this many, and one per listed object plus DISTRACTOR_CLUSTERS
# more. With 7-8 objects among unmodelled clutter, 8 dropped the smallest objects' clusters (a potted meat can,
# scissors, a banana), and those objects were placed elsewhere.
MAX_CLUSTERS = 8
DISTRACTOR_CLUSTERS = 3
MAX_CENTRES = 3  # per cluster
COARSE_POINTS = 60  # observed points per start in the cheap first fit
REFINED_PER_PLACE = 8  # starts per place that go on to the full fit
PER_CENTRE = 2  # candidates per object and start place
# Places kept per object and cluster besides the best overall: an object partly hidden behind another fits their
# joint cluster best where it also covers the other's points. The generated potted meat can, 29 % visible behind
# a clamp, had a right fit in its cluster (74 explained pixels), second to one 5 cm off covering the clamp (98).
PER_CLUSTER = 2
FIT_POINTS = 200  # observed points per candidate fit: enough to rank candidates; moves refine further
# Observed points of a cluster a refit fits candidates to. The first library fits every cluster; what a refit finds
# under this many is the rim an estimate leaves beside an object it holds a few millimetres off, and fitting every
# object to it costs as much as to a whole object's cluster (its starts do not shrink with it).
REFIT_MIN_POINTS = 50
# A refit's cluster with this share of its points within RIM_M of the estimate's own surfaces is a rim: the estimate
# nearly explains it (an object held a few millimetres off leaves a band of readings beside and before it), and its
# place is the estimate's to correct (ICP moves, settling), not a new place to fit every object to.
RIM_M = 0.01
RIM_SHARE = 0.9
MIN_TOP = 0.015  # m; lower clusters are table unevenness or flat clutter (paper, cables)
# m; a face may stand this much taller than the cluster's 95th-percentile height. The top of a bottle is a narrow
# cap that few points reach: YCB-Video's upright mustard bottle (19.1 cm) shows a cluster 17 cm high, and with
# 2 cm of slack it was never proposed standing.
FACE_SLACK = 0.04
LEVEL_BIN = 0.01  # m; heights of a cluster's horizontal surfaces are found in bins this tall
MIN_LEVEL = 40  # observed points that make a horizontal surface
MAX_LEVELS = 2  # per cluster
LEVEL_HEADINGS = 12  # headings tried on a horizontal surface, 30 degrees apart
# Headings tried at a cluster's centre and spread points, 30 degrees apart from its principal axis. A thin object
# lying flat (scissors, a clamp) barely turns under ICP: its top pins the tilt, and only its low rim the heading.
# With 4 headings (90 degrees apart), the best start of a generated frame's scissors was 17 degrees off, and ICP
# took it to 31 (docs/journal/2026-11.md, "Observed normals").
CENTRE_HEADINGS = 12
PLACE_M = 0.03  # m; candidates whose centres lie closer than this (horizontally) are at one place
# A fitted candidate is slid along its horizontal axes in these steps (each at most SLIDE_ROUNDS times) while its
# fit score rises (``slide``).
SLIDE_STEPS = (0.02, 0.01, 0.005)  # m
SLIDE_ROUNDS = 2



def elsewhere(T: np.ndarray, U: np.ndarray) -> np.ndarray:
    """Whether poses ``T`` and ``U`` (..., 4, 4, broadcastable) are at different places: their centres more than
    PLACE_M apart horizontally -> (...) bool."""
    return np.linalg.norm(T[..., :2, 3] - U[..., :2, 3], axis=-1) > PLACE_M


# A fitted candidate: its score (``fit_scores``) and pose (4, 4) in the table frame.
Candidate = tuple[float, np.ndarray]


@dataclass
class Library:
    """Per object k: ``poses[k]`` (C_k, 4, 4) candidate poses in the table frame, ``weights[k]`` (C_k,) summing
    to 1 (empty arrays when no cluster fits the object)."""

    poses: list[np.ndarray]
    weights: list[np.ndarray]

    def has(self, k: int) -> bool:
        return len(self.poses[k]) > 0

    def merged(self, other: "Library", keep: int = PER_OBJECT) -> "Library":
        """Both libraries' candidates per object, the first ``keep`` in ``place_order`` (re-normalised)."""
        poses, weights = [], []
        for k in range(len(self.poses)):
            p = np.concatenate([self.poses[k], other.poses[k]])
            w = np.concatenate([self.weights[k], other.weights[k]])
            order = place_order(p, w)[:keep]
            poses.append(p[order])
            weights.append(w[order] / w[order].sum() if len(order) else w[order])
        return Library(poses, weights)


def place_order(poses: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Candidates (poses (C, 4, 4), weights (C,)) in the order they are kept: the best of each distinct place
    (centres PLACE_M apart horizontally) by weight, then the rest by weight -> (C,) indices.

    Candidates are weighted by the observed points they explain, so the heaviest crowd the largest cluster (several
    objects touching, where every object fits somewhere) and, ranked by weight alone, pushed out a place that only
    one object explains: YCB-Video's standing marker at the image edge lost its only right candidates at the
    first refit."""
    by_weight = np.argsort(-weights, kind="stable")
    first = place_firsts(poses, weights)
    rest = [int(i) for i in by_weight if int(i) not in set(first)]
    return np.array(first + rest, dtype=int)


def place_firsts(poses: np.ndarray, weights: np.ndarray) -> list[int]:
    """The indices of the heaviest candidate (poses (C, 4, 4), weights (C,)) of each distinct place, centres at
    least PLACE_M apart horizontally, heaviest first."""
    first: list[int] = []
    for i in np.argsort(-weights, kind="stable"):
        if all(np.linalg.norm(poses[i, :2, 3] - poses[j, :2, 3]) >= PLACE_M for j in first):
            first.append(int(i))
    return first


def spread_centres(points: np.ndarray, spacing: float, limit: int) -> np.ndarray:
    """The centroid of ``points`` (P, 3) and up to ``limit`` - 1 farthest-point samples at least ``spacing``
    apart (xy) -> (C, 2)."""
    centres = [np.median(points[:, :2], axis=0)]
    xy = points[:, :2]
    d = np.linalg.norm(xy - centres[0], axis=1)
    while len(centres) < limit:
        i = int(np.argmax(d))
        if d[i] < spacing:
            break
        centres.append(xy[i])
        d = np.minimum(d, np.linalg.norm(xy - xy[i], axis=1))
    return np.array(centres)


def rectangle_heading(points: np.ndarray) -> float:
    """Heading (rad) of an edge of the minimum-area rectangle around the points' (P, 3) xy: a box's top face
    seen from above, where the principal axis of a near-square face is no axis at all."""
    xy = points[:, :2]
    try:
        ring = xy[ConvexHull(xy).vertices]
    except QhullError:  # fewer than three points, or all on a line
        return principal_heading(points)
    edges = np.roll(ring, -1, axis=0) - ring
    angles = np.arctan2(edges[:, 1], edges[:, 0])
    c, s = np.cos(angles), np.sin(angles)
    u = ring @ np.stack([c, s])  # (V, E): the hull's extent along each edge direction ...
    v = ring @ np.stack([-s, c])  # ... and across it
    return float(angles[int(np.argmin(np.ptp(u, axis=0) * np.ptp(v, axis=0)))])


def fit_scores(problem: Problem, T: np.ndarray, samples: ModelSamples, per_pixel: bool = True,
               observed: np.ndarray | None = None) -> np.ndarray:
    """Per candidate pose T (S, 4, 4) of one object: pixels it explains (observed depth on its camera-facing
    surface) less three for each pixel where the sensor sees through it (a pose that floats in front of the
    background) -> (S,). Pixels hidden behind something else count for nothing: an object may be occluded, and a
    pose buried inside another object explains little. All candidates at once, as ``project_samples`` projects
    one. ``per_pixel=False`` counts samples instead of distinct pixels: several times faster, and as good for
    ranking where the samples are sparser than the pixels. ``observed`` (h, w) m: the depth to score against
    (default the problem's; ``scenepoints.unclaimed``: what other objects leave)."""
    cam, obs = problem.render_camera, problem.observed if observed is None else observed
    h, w = obs.shape
    Tc = cam.T_cam_world[None] @ T
    Rt = np.swapaxes(Tc[:, :3, :3], 1, 2)  # batched matmul: ten times faster than the equivalent einsum
    p = samples.points @ Rt + Tc[:, None, :3, 3]  # (S, M, 3)
    n = samples.normals @ Rt
    valid = (np.einsum("smd,smd->sm", n, p) < 0) & (p[..., 2] > 1e-3)  # facing the camera, in front of it
    s, m = np.nonzero(valid)  # projected alone: half the samples face away
    p = p[s, m]
    u = np.round(p[:, 0] / p[:, 2] * cam.K[0, 0] + cam.K[0, 2]).astype(int)
    v = np.round(p[:, 1] / p[:, 2] * cam.K[1, 1] + cam.K[1, 2]).astype(int)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    s, v, u, d = s[inside], v[inside], u[inside], p[inside, 2]
    o = obs[v, u]
    if not per_pixel:
        on, through = (o > 0) & (np.abs(o - d) < EXPLAINED), (o > 0) & (o > d + SEEN_THROUGH)
        return np.bincount(s[on], minlength=len(T)) - 3.0 * np.bincount(s[through], minlength=len(T))
    key = s * (h * w) + v * w + u  # (candidate, pixel) pairs, counted once each
    on = _sorted_unique(key[(o > 0) & (np.abs(o - d) < EXPLAINED)])
    through = _sorted_unique(key[(o > 0) & (o > d + SEEN_THROUGH)])
    through = through[~_in_sorted(through, on)]
    return np.bincount(on // (h * w), minlength=len(T)) - 3.0 * np.bincount(through // (h * w), minlength=len(T))


def slide(problem: Problem, T: np.ndarray, samples: ModelSamples) -> np.ndarray:
    """Candidate poses T (S, 4, 4) of one object, each moved along its own horizontal axes (both ways, SLIDE_STEPS
    m, coarse to fine) while its ``fit_scores`` rises -> (S, 4, 4).

    Why: point-to-plane ICP cannot see a slide along the faces it fits. A box standing on its side shows its broad
    face and its top, both parallel to its length, so a fit started 2 cm along that length stays there (generated
    clutter frame 6's 89 x 73 x 28 mm box: every fit with the right heading ended 1.9-2.0 cm along its length and
    scored -59 to 3, where its true pose scores 245). Fits turned a quarter (20 and 10) were kept instead, the
    library had no right one, and the estimate put the box 28 cm away, 440 log-units below the truth. The fit score
    counts the pixels seen through the object, so it sees the slide that ICP does not; slid, those fits end within
    5 mm of the truth and score 241-253."""
    T = T.copy()
    score = fit_scores(problem, T, samples)
    for step in SLIDE_STEPS:
        for _ in range(SLIDE_ROUNDS):
            # The object's x axis, seen from above; its y axis where x is near vertical (an object standing on end).
            a = T[:, :2, 0].copy()
            steep = np.linalg.norm(a, axis=1) < 0.5
            a[steep] = T[steep, :2, 1]
            a /= np.linalg.norm(a, axis=1, keepdims=True)
            b = np.stack([-a[:, 1], a[:, 0]], axis=1)
            moved = np.repeat(T[:, None], 4, axis=1)  # (S, 4 directions, 4, 4)
            moved[:, :, :2, 3] += step * np.stack([a, -a, b, -b], axis=1)
            scores = fit_scores(problem, moved.reshape(-1, 4, 4), samples).reshape(-1, 4)
            best = np.argmax(scores, axis=1)
            rows = np.nonzero(scores[np.arange(len(T)), best] > score)[0]
            if not len(rows):
                break
            T[rows], score[rows] = moved[rows, best[rows]], scores[rows, best[rows]]
    return T


def _sorted_unique(keys: np.ndarray) -> np.ndarray:
    """The distinct values of integer ``keys`` (n,), sorted: ``np.unique``'s result. Sorting and dropping repeats is
    ten times faster than its hashing on these keys, which arrive nearly sorted (grouped by candidate): the stable
    sort (a merge sort that takes sorted runs as they are) sorts them in two thirds of quicksort's time."""
    keys = np.sort(keys, kind="stable")
    return keys[np.concatenate(([True], keys[1:] != keys[:-1]))] if len(keys) else keys


def _in_sorted(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Which of ``a`` (n,) are in ``b`` (m,), sorted -> (n,) bool: ``np.isin`` by binary search."""
    at = np.minimum(np.searchsorted(b, a), max(len(b) - 1, 0))
    return (b[at] == a) if len(b) else np.zeros(len(a), dtype=bool)


def build_library(problem: Problem, clusters: list[np.ndarray], geometry: SearchGeometry,
                  memo: dict | None = None, run: Callable | None = None) -> Library:
    """Candidate poses for every object from the ``clusters`` (list of (P_i, 3), largest first); ICP against
    all observed points (``geometry.points``) near each start. -> Library.

    Coarse to fine: every start gets a few cheap ICP steps on a few points and is scored; only the best
    ``REFINED_PER_PLACE`` of each place go on to the full ICP. On the real dev frames this keeps as many right
    candidates as fitting every start fully (21 against 22 of 50 objects) at a sixth of the time.

    ``memo``: a dict kept by the caller across calls with the same problem, geometry and models. A cluster's
    candidates depend on nothing but the cluster, so a cluster seen before (unmodelled clutter that no estimate
    explains stays the same cluster refit after refit) is not fitted again; the library is the same with or
    without it. ``run(fn, calls)``: how the fits are run (``Evaluator.map``; default ``evaluation.run_here``), the
    same library either way."""
    cloud, rest, samples, hulls = geometry.points, geometry.rest, geometry.samples, geometry.hulls
    K = len(rest)
    found: list[list[Candidate]] = [[] for _ in range(K)]
    clusters = fitted_clusters(clusters, K)
    keys = [hashlib.sha1(np.ascontiguousarray(c, dtype=np.float64).tobytes()).hexdigest() for c in clusters]
    memo = {} if memo is None else memo
    # Every (cluster, object) fit not remembered, all at once: ``run`` may spread them over the workers.
    new = list(dict.fromkeys(key for key in keys if key not in memo))
    first = {key: clusters[keys.index(key)] for key in new}
    fits = (run or run_here(problem))(cluster_candidates, [(first[key], cloud, rest[k], samples[k], hulls[k])
                                                           for key in new for k in range(K)])
    for i, key in enumerate(new):
        memo[key] = fits[i * K:(i + 1) * K]
    for key in keys:
        for k in range(K):
            found[k] += memo[key][k]
    poses, weights = [], []
    for k in range(K):
        # The best fits overall, then the best of each cluster's first PER_CLUSTER places: a small object fits a
        # large flat surface as well as its own cluster (better, where something hides part of it), so the best
        # fits overall can all lie on other objects: on generated clutter the gelatin box had none within 13 cm of
        # where it lay. The merge at the next refit keeps the best of each place (``place_order``).
        best = _distinct(sorted(found[k], key=lambda c: -c[0]), PER_OBJECT)
        firsts = sorted([c for key in keys for c in _places(memo[key][k])], key=lambda c: -c[0])
        kept = _distinct(best + firsts, len(best) + len(firsts))
        poses.append(np.stack([c[1] for c in kept]) if kept else np.zeros((0, 4, 4)))
        weights.append(candidate_weights(np.array([c[0] for c in kept])))
    return Library(poses, weights)


def candidate_weights(scores: np.ndarray) -> np.ndarray:
    """Library weights (C,), summing to 1, of candidates scored ``scores`` (C,) by ``fit_scores``.

    Flat on purpose: a large object fits well into another object's cluster too, and only the whole scene
    (physics, the likelihood) can tell which cluster is whose. Softmax in units of half the best score, mixed with
    uniform, so that no candidate is starved."""
    if not len(scores):
        return np.zeros(0)
    w = np.exp((scores - scores.max()) / max(0.5 * abs(scores.max()), 1.0))
    w = 0.7 * w / w.sum() + 0.3 / len(w)
    return w / w.sum()


def rims(clusters: list[np.ndarray], scene: np.ndarray, samples: list[ModelSamples]) -> np.ndarray:
    """Which ``clusters`` (list of (P_i, 3), table frame) are rims of ``scene`` (K, 4, 4): RIM_SHARE of their
    points within RIM_M of some object's surface samples -> (len(clusters),) bool."""
    if not clusters:
        return np.zeros(0, dtype=bool)
    surface = np.concatenate([s.points @ T[:3, :3].T + T[:3, 3] for s, T in zip(samples, scene)])
    tree = cKDTree(surface)
    return np.array([np.mean(tree.query(c, distance_upper_bound=RIM_M)[0] < RIM_M) >= RIM_SHARE for c in clusters],
                    dtype=bool)


def fitted_clusters(clusters: list[np.ndarray], n_objects: int) -> list[np.ndarray]:
    """The clusters (list of (P_i, 3), largest first) that candidates are fitted to: those that rise MIN_TOP above
    the table, at most MAX_CLUSTERS, or one per object and DISTRACTOR_CLUSTERS more where that is more."""
    clusters = [c for c in clusters if np.percentile(c[:, 2], 95) >= MIN_TOP]
    return clusters[:max(MAX_CLUSTERS, n_objects + DISTRACTOR_CLUSTERS)]


def cluster_candidates(problem: Problem, cluster: np.ndarray, cloud: ScenePoints, rest: RestingPoses,
                       samples: ModelSamples, hull: np.ndarray) -> list[Candidate]:
    """One object's scored candidates (``Candidate``) fitted at one ``cluster`` (P, 3) to the observed points
    ``cloud``: the best PER_CENTRE distinct ones of each start place (``icp_starts``), place by place, and of a
    thin object's outline aligned with the cluster (``footprint_starts``, not fitted further)."""
    reach = float(np.max(np.linalg.norm(hull[:, :2], axis=1)))
    starts, place = icp_starts(cluster, rest, hull, reach)
    if not starts:
        return []
    starts = np.stack(starts)
    points, normals = near(cloud, starts[:, :3, 3], reach + NEAR)
    rough, _ = icp_batch(points, samples, starts, iterations=3, max_points=COARSE_POINTS, stages=STAGES[:1],
                         viewpoint=cloud.viewpoint, normals=normals)
    rough_score = fit_scores(problem, rough, samples)
    place = np.asarray(place)
    chosen = np.concatenate([np.nonzero(place == p)[0][np.argsort(-rough_score[place == p], kind="stable")
                                                        [:REFINED_PER_PLACE]] for p in np.unique(place)])
    fitted, inliers = icp_batch([points[i] for i in chosen], samples, rough[chosen], max_points=FIT_POINTS,
                                viewpoint=cloud.viewpoint, normals=[normals[i] for i in chosen])
    ok = (inliers >= 10) & np.all(np.isfinite(fitted), axis=(1, 2))
    fitted, fitted_place = slide(problem, fitted[ok], samples), place[chosen][ok]
    # A thin object lying flat: its outline's alignments, one more place, as they are (ICP would let them slide).
    flat = footprint_starts(cluster, cloud, rest, samples, hull, reach)
    if flat:
        fitted = np.concatenate([fitted, np.stack(flat)])
        fitted_place = np.concatenate([fitted_place, np.full(len(flat), place.max() + 1)])
    scores = fit_scores(problem, fitted, samples)
    # The best of each start place, so that in a cluster of several objects touching, the largest object's
    # surface (where a smaller object also fits well) cannot crowd out the others.
    out: list[Candidate] = []
    for p in np.unique(fitted_place):
        at = np.nonzero(fitted_place == p)[0]
        at = at[np.argsort(-scores[at], kind="stable")]
        out += _distinct([(float(scores[i]), fitted[i]) for i in at], PER_CENTRE)
    return out


def icp_starts(cluster: np.ndarray, rest: RestingPoses, hull: np.ndarray, reach: float
            ) -> tuple[list[np.ndarray], list[int]]:
    """One object's ICP starts (4, 4) at one ``cluster`` (P, 3), and the start place of each:
    - at the cluster's centroid and spread points, on every face on which the object is no taller than the
      cluster, in CENTRE_HEADINGS headings from the cluster's principal axis; where the cluster is clearly taller
      than the object, also on top, its upper face at the cluster's top;
    - on top of something: at each of the cluster's horizontal surfaces (``_levels``), the object's upper face
      there, in LEVEL_HEADINGS headings from the surface's minimum-area rectangle (one more place each)."""
    starts: list[np.ndarray] = []
    place: list[int] = []
    heights = np.array([height(R, hull) for R in rest.rotations])
    n_places = 0

    def add(centres: np.ndarray, bases: list[tuple[int, float]], heading: float, turns: int) -> None:
        nonlocal n_places
        for centre in centres:
            for f, base in bases:
                for i in range(turns):
                    R = rot_z(heading + i * 2 * np.pi / turns) @ rest.rotations[f]
                    starts.append(make_pose(R, np.array([centre[0], centre[1], base + rest.heights[f]])))
                    place.append(n_places)
            n_places += 1

    top = float(np.percentile(cluster[:, 2], 95))
    faces = np.nonzero(heights <= top + FACE_SLACK)[0]
    bases = [(f, 0.0) for f in (faces if len(faces) else [int(np.argmin(heights))])]
    # Where the cluster is clearly taller, the object may stand on something, so it also starts on top.
    bases += [(f, top - heights[f]) for f in faces if top > heights[f] + 0.02]
    add(spread_centres(cluster, 1.2 * reach, MAX_CENTRES), bases, principal_heading(cluster), CENTRE_HEADINGS)
    # An object on top of another shows as a horizontal surface of their joint cluster (many points at one
    # height), which the cluster's centre and rim miss when the cluster also holds objects beside them:
    # YCB-Video's pudding box lies on the wood block, which touches the can and the banana, and no start
    # came within 6 cm of it. The surface's rectangle gives a heading only roughly (other objects' points
    # share the height), so more headings are tried there.
    for level, upper in _levels(cluster):
        on = [(f, level - heights[f]) for f in faces if level > heights[f] + 0.02]
        if on:
            add(spread_centres(upper, 1.2 * reach, 1), on, rectangle_heading(upper), LEVEL_HEADINGS)
    return starts, place


def _levels(cluster: np.ndarray) -> list[tuple[float, np.ndarray]]:
    """The heights (m) of a cluster's (P, 3) horizontal surfaces, with their points: histogram peaks of the
    points' heights (LEVEL_BIN bins, at least MIN_LEVEL points, the MAX_LEVELS fullest) -> [(height, (Q, 3))]."""
    z = cluster[:, 2]
    edges = np.arange(0.0, z.max() + 2 * LEVEL_BIN, LEVEL_BIN)
    count, _ = np.histogram(z, edges)
    padded = np.concatenate([[0], count, [0]])
    peak = (count >= MIN_LEVEL) & (count >= padded[:-2]) & (count > padded[2:])
    out = []
    for b in sorted(np.nonzero(peak)[0], key=lambda b: -count[b])[:MAX_LEVELS]:
        at = (z >= edges[b]) & (z < edges[b + 1])
        out.append((float(np.median(z[at])), cluster[at]))
    return out


def _places(candidates: list[Candidate]) -> list[Candidate]:
    """The best candidate of each of the first PER_CLUSTER distinct places (``place_firsts``), best first."""
    if not candidates:
        return []
    first = place_firsts(np.stack([c[1] for c in candidates]), np.array([c[0] for c in candidates]))
    return [candidates[i] for i in first[:PER_CLUSTER]]


def _distinct(candidates: list[Candidate], keep: int) -> list[Candidate]:
    """The best candidates, skipping any within 1.5 cm and 15 degrees of a better one."""
    out: list[Candidate] = []
    for c in candidates:
        T = c[1]
        if all(np.linalg.norm(T[:3, 3] - U[:3, 3]) > 0.015
               or rotation_angle(T[:3, :3].T @ U[:3, :3]) > np.radians(15) for _, U in out):
            out.append(c)
        if len(out) >= keep:
            break
    return out


def sample_candidates(rng: np.random.Generator, library: Library, k: int, n: int) -> np.ndarray:
    """n poses of object k drawn from its library with jitter -> (n, 4, 4)."""
    c = rng.choice(len(library.weights[k]), size=n, p=library.weights[k])
    out = library.poses[k][c].copy()
    out[:, :3, 3] += rng.normal(scale=JITTER_POS, size=(n, 3))
    out[:, :3, :3] = euler_to_matrix(rng.normal(scale=JITTER_ANG, size=(n, 3))) @ out[:, :3, :3]
    return out


def log_density(library: Library, k: int, T: np.ndarray) -> float:
    """log of object k's library mixture density at pose T (4, 4), up to a constant shared by all poses."""
    P = library.poses[k]
    d2 = np.sum((P[:, :3, 3] - T[:3, 3]) ** 2, axis=1)
    a = rotation_angle(np.swapaxes(P[:, :3, :3], 1, 2) @ T[:3, :3])
    terms = np.log(library.weights[k]) - 0.5 * d2 / JITTER_POS**2 - 0.5 * a * a / JITTER_ANG**2
    m = terms.max()
    return float(m + np.log(np.sum(np.exp(terms - m))))


def overlaps(T: np.ndarray, others: np.ndarray, radius: float, other_radii: np.ndarray) -> bool:
    """Whether an object of ``radius`` (m) at pose T (4, 4) would sit deep inside one of ``others`` (J, 4, 4)
    of ``other_radii`` (J,): centres closer than 40 % of the radii's sum (stacked or touching objects are
    farther apart than that)."""
    if len(others) == 0:
        return False
    d = np.linalg.norm(others[:, :3, 3] - T[:3, 3], axis=1)
    return bool(np.any(d < 0.4 * (radius + other_radii)))


def draw_compatible(rng: np.random.Generator, library: Library, k: int, others: np.ndarray, radii: np.ndarray,
                    others_k: np.ndarray, tries: int = 8) -> np.ndarray:
    """A pose of object k from its library that does not sit inside the objects ``others`` (J, 4, 4) (indices
    ``others_k`` (J,) into ``radii`` (K,)); the last draw if every try overlaps -> (4, 4).

    The others are the same in the forward and the reverse move, so restricting the draw to the poses
    compatible with them changes the mixture density by a factor that cancels in the log-q correction."""
    for _ in range(tries):
        T = sample_candidates(rng, library, k, 1)[0]
        if not overlaps(T, others, radii[k], radii[others_k]):
            break
    return T


def sequential_start(rng: np.random.Generator, library: Library, n: int, radii: np.ndarray, take: np.ndarray,
                     uniform: np.ndarray) -> np.ndarray:
    """n initial scenes (n, K, 4, 4): objects in a random order each take a library pose compatible with those
    already placed, where ``take`` (n, K) says so; the others keep their ``uniform`` (n, K, 4, 4) start."""
    out = uniform.copy()
    K = uniform.shape[1]
    for i in range(n):
        placed: list[int] = []
        for k in rng.permutation(K):
            if take[i, k] and library.has(k):
                idx = np.array(placed, dtype=int)
                out[i, k] = draw_compatible(rng, library, k, out[i, idx], radii, idx)
                placed.append(int(k))
    return out


def propose_data(rng: np.random.Generator, parents: np.ndarray, library: Library, weights: np.ndarray,
                 radii: np.ndarray) -> Proposal:
    """One object per particle (drawn by ``weights`` (K,) among objects with candidates) takes a pose from its
    library that does not sit inside another object (``radii`` (K,) m); the others stay. An independence move:
    log-q correction log q(x_k) - log q(x*_k). (B, K, 4, 4) -> Proposal."""
    K = parents.shape[1]
    has = np.array([library.has(k) for k in range(K)])
    out = parents.copy()
    log_q = np.zeros(len(parents))
    if not has.any():
        return Proposal(out, log_q)
    ks = pick_objects(rng, len(parents), np.where(has, weights, 0.0))
    for b, k in enumerate(ks):
        others = np.array([j for j in range(K) if j != k], dtype=int)
        new = draw_compatible(rng, library, k, parents[b, others], radii, others)
        log_q[b] = log_density(library, k, parents[b, k]) - log_density(library, k, new)
        out[b, k] = new
    return Proposal(out, log_q)
