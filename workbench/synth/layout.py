"""Layouts: the objects of a scene placed by *relations* (touch / stack / slant / hide / free), each new object
moved along one degree of freedom until it just touches its partner; settled, and kept only when its relations
still hold.

The relations each category is built from, and the objects suited to them, are drawn here too."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.geometry import make_pose, rot_z
from workbench.synth.config import HANDLE_CATEGORIES
from workbench.synth.objects import (
    BOX_BY_ID,
    BOXES,
    EZ,
    MUG,
    OBJECT_BY_ID,
    OBJECTS,
    SMALL,
    TALL,
    Box,
    Item,
    horizontal_faces,
    lying_rotation,
    reach,
    resting_rotation,
    support_half_extent,
    tilt_deg,
)
from workbench.synth.sim import Sim, bisect_contact


@dataclass
class Placed:
    """One object of a layout. ``relation``: how it was placed relative to ``parent`` (index into the layout;
    -1 for the base and for objects standing free)."""

    item: Item
    T: np.ndarray  # (4, 4) T_world_obj
    relation: str = "base"  # base | touch | stack | slant | hide | free | lie (free, in any stable pose)
    parent: int = -1
    body: int = -1


# ----------------------------------------------------------------------------------------------------------------
# Relations: each places a new box against a box already resting flat on the table


def side_normals(p: Placed) -> list[np.ndarray]:
    """Horizontal directions (world, unit) to place a neighbour along: a box's four side faces; all around a
    round object, eight directions turned with it."""
    if p.item.kind == "box":
        return horizontal_faces(p.T[:3, :3])
    yaw = np.arctan2(p.T[1, 0], p.T[0, 0])
    return [np.array([np.cos(a), np.sin(a), 0.0]) for a in yaw + np.arange(8) * np.pi / 4]


def place_touch(sim: Sim, rng, parent: Placed, box: Item, body: int, edge: bool, hide: bool = False):
    """``box`` on the table against a side face of ``parent``: face to face, or (``edge``) turned so that a
    vertical edge meets the face. ``hide``: lying flat, aligned and centred on the face, to be hidden behind it.
    A round object stands upright, turned at random. -> (T_world_obj, outward normal of the parent's face) or
    None."""
    c_A, R_A = parent.T[:3, 3], parent.T[:3, :3]
    faces = side_normals(parent)
    n = faces[rng.integers(len(faces))]
    t = np.cross(EZ, n)
    up = int(np.argmin(box.extents)) if hide else int(rng.integers(3))
    yaw_A = np.arctan2(n[1], n[0])
    yaw = yaw_A + rng.integers(4) * np.pi / 2 + (rng.uniform(np.radians(20), np.radians(70)) if edge else 0.0)
    R = resting_rotation(up, yaw, bool(rng.integers(2)))
    if box.kind != "box":
        R = rot_z(yaw)
    hA_n = reach(parent.item, R_A, n)
    hA_t = reach(parent.item, R_A, t)
    hB_n = reach(box, R, -n)
    hB_t = reach(box, R, t)
    if hide:
        room = max(hA_t - hB_t, 0.0)
        lateral = rng.uniform(-room, room) * 0.5
    else:
        lateral = rng.uniform(-0.6, 0.6) * hA_t
    z = reach(box, R, -EZ) + sim.cfg.lift

    def pose_at(s: float) -> np.ndarray:
        p = c_A + n * s + t * lateral
        return make_pose(R, np.array([p[0], p[1], z]))

    T = bisect_contact(sim, body, parent.body, pose_at, hA_n + hB_n + 0.05, hA_n + hB_n - 0.01)
    return None if T is None else (T, n)


def place_stack(sim: Sim, rng, parent: Placed, box: Item, body: int):
    """``box`` lowered onto the top of box ``parent``, its centre out towards one edge (it may overhang). A round
    object stands upright."""
    c_A, R_A = parent.T[:3, 3], parent.T[:3, :3]
    faces = horizontal_faces(R_A)
    n = faces[rng.integers(len(faces))]
    t = np.cross(EZ, n)
    up = int(rng.integers(3))
    R = resting_rotation(up, np.arctan2(n[1], n[0]) + rng.uniform(-np.pi, np.pi), bool(rng.integers(2)))
    if box.kind != "box":
        R = rot_z(np.arctan2(R[1, 0], R[0, 0]))
    hA_n = reach(parent.item, R_A, n)
    hA_t = reach(parent.item, R_A, t)
    top = c_A[2] + reach(parent.item, R_A, EZ)
    hB_z = reach(box, R, -EZ)
    xy = c_A + n * hA_n * rng.uniform(0.45, 0.85) + t * hA_t * rng.uniform(-0.3, 0.3)

    def pose_at(s: float) -> np.ndarray:
        return make_pose(R, np.array([xy[0], xy[1], top + hB_z + s]))

    return bisect_contact(sim, body, parent.body, pose_at, 0.05, -0.01)


def place_slant(sim: Sim, rng, parent: Placed, box: Box, body: int):
    """``box`` standing on its bottom edge on the table beside ``parent`` and tipped over onto it."""
    c_A, R_A = parent.T[:3, 3], parent.T[:3, :3]
    faces = horizontal_faces(R_A)
    n = faces[rng.integers(len(faces))]
    t = np.cross(EZ, n)
    e = np.asarray(box.extents)
    long, thin = int(np.argmax(e)), int(np.argmin(e))
    wide = 3 - long - thin
    R0 = np.zeros((3, 3))
    R0[:, long], R0[:, thin], R0[:, wide] = EZ, n, t
    if np.linalg.det(R0) < 0:
        R0[:, wide] = -t
    h, th = e[long], e[thin]
    H_A = c_A[2] + support_half_extent(R_A, parent.item.extents, EZ)
    theta = np.radians(rng.uniform(15.0, 45.0))
    # Pivot distance from the parent's face for the intended lean: the top corner meets the face when the parent is
    # taller than the leaning box's top, else the leaning face rests on the parent's top edge.
    D = h * np.sin(theta) if h * np.cos(theta) <= H_A else H_A * np.tan(theta)
    face = c_A + n * support_half_extent(R_A, parent.item.extents, n)
    pivot = face + n * D + t * rng.uniform(-0.4, 0.4) * support_half_extent(R_A, parent.item.extents, t)
    pivot[2] = sim.cfg.lift
    c0 = pivot + n * th / 2 + EZ * h / 2
    k = np.cross(n, EZ)  # turning about k carries the top towards the parent

    def pose_at(a: float) -> np.ndarray:
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        Rk = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
        return make_pose(Rk @ R0, pivot + Rk @ (c0 - pivot))

    return bisect_contact(sim, body, parent.body, pose_at, 0.0, np.radians(85.0))


# ----------------------------------------------------------------------------------------------------------------
# Layouts per category


def _draw_relations(category: str, rng) -> list[str]:
    """The relations (besides the base object) a scene of ``category`` is built from."""
    single = {"touching": "touch", "stacked": "stack", "slant": "slant", "occluded": "hide"}
    if category in single:
        return [single[category]]
    if category == "clutter":  # 4-6 objects, some touching and some stacked, the rest standing free
        n = int(rng.integers(3, 6))
        while True:
            rel = [str(r) for r in rng.choice(["touch", "stack", "free"], size=n)]
            if "touch" in rel and "stack" in rel:
                return rel
    if category == "lying":  # 2-4 objects, each lying free in one of its stable poses
        return ["lie"] * int(rng.integers(1, 4))
    if category in HANDLE_CATEGORIES:  # the mug and 0-2 boxes standing free around it
        return ["free"] * int(rng.integers(0, 3))
    if category == "mixed":  # 2-3 objects, boxes and round ones, in any relation
        return [str(r) for r in rng.choice(["touch", "stack", "free"], size=int(rng.integers(1, 3)))]
    n = {"three": 2, "four": 3}[category]
    while True:
        rel = [str(r) for r in rng.choice(["touch", "stack", "slant", "hide"], size=n)]
        if len(set(rel)) >= 2 and rel.count("hide") <= 1:
            return rel


def _draw_boxes(relations: list[str], rng) -> list[Box]:
    """Distinct boxes suited to the relations: a tall box hides a small one, a long one leans, a stacked box is
    the smaller of its pair."""
    for _ in range(100):
        ids = [int(i) for i in rng.permutation([b.obj_id for b in BOXES])[: len(relations) + 1]]
        ok = "hide" not in relations or ids[0] in TALL  # the hiding box is the base, standing upright
        for j, rel in enumerate(relations, start=1):
            if rel == "hide":
                ok &= ids[j] in SMALL
            if rel == "slant":
                ok &= ids[j] in TALL
        if ok:
            return [BOX_BY_ID[i] for i in ids]
    raise RuntimeError(f"no boxes fit the relations {relations}")


def _draw_items(category: str, relations: list[str], rng, pool: tuple[Item, ...] = ()) -> list[Item]:
    """Distinct objects for the relations. ``lying`` draws from ``pool`` (default: every built-in object);
    ``clutter`` and ``mixed`` from the boxes and the round objects, at least one of each, with a box as the base;
    the paper's categories use boxes only (:func:`_draw_boxes`)."""
    if category == "lying":
        pool = pool or OBJECTS
        return [pool[int(i)] for i in rng.permutation(len(pool))[: len(relations) + 1]]
    if category in HANDLE_CATEGORIES:  # the mug first: the camera is drawn about its handle
        return [MUG] + [BOX_BY_ID[int(i)] for i in rng.permutation([b.obj_id for b in BOXES])[: len(relations)]]
    if category not in ("clutter", "mixed"):
        return _draw_boxes(relations, rng)
    while True:
        ids = [int(i) for i in rng.permutation([o.obj_id for o in OBJECTS])[: len(relations) + 1]]
        items = [OBJECT_BY_ID[i] for i in ids]
        if items[0].kind == "box" and any(o.kind != "box" for o in items):
            return items


def _parent_ok(rel: str, parent: Placed, child: Item) -> bool:
    """Can ``child`` be placed by ``rel`` against ``parent``? Parents rest flat on the table (not stacked or
    leaning); a hiding parent stands upright; a stacked child is the smaller one, on a box."""
    if parent.relation in ("stack", "slant"):
        return False
    if rel == "hide":
        return parent.item.obj_id in TALL and abs(parent.T[2, int(np.argmax(parent.item.extents))]) > 0.999
    if rel == "stack":
        return parent.item.kind == "box" and np.prod(child.extents) < np.prod(parent.item.extents)
    if rel == "slant":
        return parent.item.kind == "box"
    return True


def _base_pose(box: Item, relations: list[str], rng, lift: float) -> np.ndarray:
    """The first object: in a stable pose when the others lie (``lie``); a round one upright; a box upright when a
    box is to hide behind it, on its largest face when one is stacked on it first (a broad support), else on a
    random face."""
    if "lie" in relations or box.kind != "box":
        R = lying_rotation(box, rng) if "lie" in relations else rot_z(rng.uniform(-np.pi, np.pi))
        xy = rng.uniform(-0.05, 0.05, size=2)
        return make_pose(R, np.array([xy[0], xy[1], reach(box, R, -EZ) + lift]))
    if "hide" in relations:
        up = int(np.argmax(box.extents))
    elif relations[0] == "stack":
        up = int(np.argmin(box.extents))
    else:
        up = int(rng.integers(3))
    R = resting_rotation(up, rng.uniform(-np.pi, np.pi), bool(rng.integers(2)))
    xy = rng.uniform(-0.05, 0.05, size=2)
    return make_pose(R, np.array([xy[0], xy[1], support_half_extent(R, box.extents, EZ) + lift]))


def place_free(sim: Sim, rng, layout: list[Placed], item: Item, body: int, clearance: float = 0.02,
               lying: bool = False):
    """``item`` standing on the table 10-25 cm from the layout's centre, at least ``clearance`` from everything
    (a box on a random face, a round object upright; with ``lying``, any object in one of its stable poses).
    -> T_world_obj or None."""
    centre = np.mean([p.T[:3, 3] for p in layout], axis=0)
    for _ in range(20):
        yaw = rng.uniform(-np.pi, np.pi)
        if lying:
            R = lying_rotation(item, rng)
        else:
            R = resting_rotation(int(rng.integers(3)), yaw, bool(rng.integers(2))) if item.kind == "box" else rot_z(yaw)
        a, r = rng.uniform(-np.pi, np.pi), rng.uniform(0.10, 0.25)
        T = make_pose(R, np.array([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a),
                                   reach(item, R, -EZ) + sim.cfg.lift]))
        sim.set_pose(body, T)
        if all(sim.distance(body, p.body) > clearance for p in layout):
            return T
    return None


def draw_layout(sim: Sim, category: str, rng) -> tuple[list[Placed], list[np.ndarray]] | None:
    """Place objects in ``sim`` by the category's relations (not yet settled). -> (layout, hide normals) or None."""
    relations = _draw_relations(category, rng)
    items = _draw_items(category, relations, rng, sim.cfg.objects)
    base = Placed(items[0], _base_pose(items[0], relations, rng, sim.cfg.lift),
                  "lie" if "lie" in relations else "base")
    base.body = sim.add_item(base.item, base.T)
    layout, hide_normals = [base], []
    for rel, item in zip(relations, items[1:]):
        body = sim.add_item(item, make_pose(np.eye(3), [5.0, 5.0, 5.0]))  # parked far away until placed
        if rel in ("free", "lie"):
            T = place_free(sim, rng, layout, item, body, lying=rel == "lie")
            if T is None:
                return None
            layout.append(Placed(item, T, rel, -1, body))
            continue
        parents = [i for i, p in enumerate(layout) if _parent_ok(rel, p, item)]
        if not parents:
            return None
        i_parent = parents[rng.integers(len(parents))]
        parent = layout[i_parent]
        if rel == "touch":
            placed = place_touch(sim, rng, parent, item, body, edge=bool(rng.integers(2)))
            T = None if placed is None else placed[0]
        elif rel == "hide":
            placed = place_touch(sim, rng, parent, item, body, edge=False, hide=True)
            T = None if placed is None else placed[0]
            if placed is not None:
                hide_normals.append(placed[1])
        elif rel == "stack":
            T = place_stack(sim, rng, parent, item, body)
        else:
            T = place_slant(sim, rng, parent, item, body)
        if T is None:
            return None
        # The new object may touch only its partner (and the table): anything else makes an unplanned relation.
        if any(sim.distance(body, p.body) < 2 * sim.cfg.contact_tol for p in layout if p is not parent):
            return None
        layout.append(Placed(item, T, rel, i_parent, body))
    return layout, hide_normals


def relations_hold(sim: Sim, layout: list[Placed]) -> bool:
    """After settling: is every relation of the layout still true, and everything on the table?"""
    c = sim.cfg

    def flat(p: Placed) -> bool:
        return tilt_deg(p.T[:3, :3]) < c.flat_tol
    for p in layout:
        x, y, z = p.T[:3, 3]
        if abs(x) > c.table_size[0] / 2 - 0.02 or abs(y) > c.table_size[1] / 2 - 0.02 or z < 0:
            return False
        on_table = sim.touching(p.body, sim.table)
        if p.relation == "lie":  # at rest (settled) on the table in whatever pose
            ok = on_table
        elif p.relation in ("base", "free"):
            ok = on_table and flat(p)
        else:
            parent = layout[p.parent]
            ok = sim.touching(p.body, parent.body)
            if p.relation in ("touch", "hide"):
                ok = ok and on_table and flat(p) and flat(parent)
            elif p.relation == "stack":  # resting on the other box, not on the table
                ok = ok and not on_table and flat(p)
            elif p.relation == "slant":
                ok = ok and on_table and c.slant_range[0] <= tilt_deg(p.T[:3, :3]) <= c.slant_range[1]
        if not ok:
            return False
    return True


def settle_layout(sim: Sim, layout: list[Placed]) -> bool:
    """Simulate to rest and store the settled poses in the layout. False if it never came to rest."""
    ok = sim.settle([p.body for p in layout])
    for p in layout:
        p.T = sim.pose(p.body)
    return ok
