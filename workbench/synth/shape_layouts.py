"""Layouts of the categories of real shapes (``SHAPE_CATEGORIES``), drawn from given models (``make-scenes
--models``) that collide as their V-HACD pieces (``bodies``), placed by ``resting``:

- ``ycb_clutter``: 6-8 models (as many as are given, if fewer), each in a stable pose, some slid against another
  until they touch, the rest standing free nearby;
- ``raised``: 2-4 models on the top of a large box on the table (``SynthConfig.raised_extents``). The box is part
  of the environment: in the depth and the physics, listed in scene_distractors.json as the "support", not in
  scene_gt.json;
- ``leaning``: a box leaning on a vessel (upright or upturned) or on another box, and 0-2 more objects;
- ``tools``: 1-2 tools (``roles``) lying in stable poses, and 1-3 other objects.

A scene is kept only when, settled, it still is what it was drawn as (``holds``): every object at rest on its
surface and touching exactly the objects it was placed against, a leaning box tilted 10-80 degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.errors import InputError
from workbench.geometry import make_pose, rot_z
from workbench.synth.config import SynthConfig
from workbench.synth.distractors import Distractor
from workbench.synth.layout import Placed
from workbench.synth.objects import MeshItem, tilt_deg
from workbench.synth.resting import (
    Surface,
    clear_of,
    place_against,
    place_free,
    place_lean,
    posed_points,
)
from workbench.synth.roles import BOX, TOOL, VESSEL, box_frame, role
from workbench.synth.sim import Sim

PARKED = make_pose(np.eye(3), np.array([5.0, 5.0, 5.0]))  # where a body waits until it is placed
TABLE_MARGIN = 0.02  # m: objects stand this far inside the table's edges
TOP_MARGIN = 0.005  # m: ... and inside a raised box's top
STABLE_TOL = 5.0  # degrees an object placed in a stable pose may tip while the scene settles
PLACE_TRIES = 5  # placements tried per object (each a new pose and direction) before the layout is redrawn


@dataclass
class ShapeLayout:
    """A layout of real shapes: the objects, the surface they rest on, the environment that is no object of
    interest (the raised box), and each object's up direction in its own frame as placed (K, 3)."""

    layout: list[Placed]
    surface: Surface
    environment: list[Distractor]
    placed_up: np.ndarray


def leaners(pool: tuple[MeshItem, ...]) -> list[MeshItem]:
    """The boxes that can lean: at least half again as long as they are thick."""
    return [o for o in pool if role(o) == BOX and max(box_frame(o)[1]) >= 1.5 * min(box_frame(o)[1])]


def check_models(category: str, pool: tuple[MeshItem, ...]) -> None:
    """Refuse, naming the option, models of which ``category`` cannot be drawn."""
    partners = [o for o in pool if role(o) in (BOX, VESSEL)]
    need = {
        "ycb_clutter": (len(pool) >= 2, "at least two models"),
        "raised": (len(pool) >= 2, "at least two models"),
        "tools": (any(role(o) == TOOL for o in pool) and any(role(o) != TOOL for o in pool),
                  "a tool (a concave model that is no vessel, e.g. a drill or a clamp) and another model"),
        "leaning": (any(p is not b for b in leaners(pool) for p in partners),
                    "a box to lean (filling its bounding box, half again as long as thick) and another box or a "
                    "vessel to lean on"),
    }
    ok, what = need[category]
    if not ok:
        raise InputError("--models", f"{category} needs {what} among the models")


def _pick(rng, items: list[MeshItem], n: int) -> list[MeshItem]:
    """``n`` of ``items`` (all of them if fewer), in random order."""
    return [items[int(i)] for i in rng.permutation(len(items))[:n]]


def _others(rng, placed: list[tuple[MeshItem, str, int]], items: list[MeshItem],
            p_touch: float) -> list[tuple[MeshItem, str, int]]:
    """Plan steps for ``items`` after ``placed``: each slid against an earlier object with probability
    ``p_touch`` (not against a leaning box: it would push it over), else free."""
    plan = list(placed)
    for item in items:
        parents = [j for j, (_, rel, _) in enumerate(plan) if rel != "lean"]
        if plan and rng.random() < p_touch:
            plan.append((item, "touch", parents[int(rng.integers(len(parents)))]))
        else:
            plan.append((item, "lie", -1))
    return plan


def draw_plan(category: str, rng, pool: tuple[MeshItem, ...], cfg: SynthConfig) -> list[tuple[MeshItem, str, int]]:
    """What a scene of ``category`` holds: (model, relation "lie" | "touch" | "lean", parent index or -1), in
    placing order."""
    pool = list(pool)
    if category == "ycb_clutter":
        lo, hi = cfg.clutter_count
        items = _pick(rng, pool, int(rng.integers(lo, hi + 1)))
        plan = _others(rng, [(items[0], "lie", -1)], items[1:], 0.4)
        if all(rel != "touch" for _, rel, _ in plan):  # some touching
            k = int(rng.integers(1, len(plan)))
            plan[k] = (plan[k][0], "touch", int(rng.integers(k)))
        return plan
    if category == "raised":
        items = _pick(rng, pool, int(rng.integers(2, 5)))
        return _others(rng, [(items[0], "lie", -1)], items[1:], 0.4)
    if category == "tools":
        tools = _pick(rng, [o for o in pool if role(o) == TOOL], int(rng.integers(1, 3)))
        others = _pick(rng, [o for o in pool if role(o) != TOOL], int(rng.integers(1, 4)))
        return _others(rng, [(tools[0], "lie", -1)], tools[1:] + others, 0.4)
    leaner = _pick(rng, leaners(pool), 1)[0]
    vessels = [o for o in pool if role(o) == VESSEL]
    boxes = [o for o in pool if role(o) == BOX and o is not leaner]
    # A vessel half the time where there is one (a box on an upturned bowl): YCB has six boxes and two vessels.
    partner = _pick(rng, vessels if vessels and (not boxes or rng.random() < 0.5) else boxes, 1)[0]
    rest = _pick(rng, [o for o in pool if o is not leaner and o is not partner], int(rng.integers(0, 3)))
    return _others(rng, [(partner, "lie", -1), (leaner, "lean", 0)], rest, 0.4)


def _table(sim: Sim) -> Surface:
    """The table's top as a surface, its edges ``TABLE_MARGIN`` in."""
    half = (sim.cfg.table_size[0] / 2 - TABLE_MARGIN, sim.cfg.table_size[1] / 2 - TABLE_MARGIN)
    return Surface(sim.table, np.eye(4), half)


def _raised_box(sim: Sim, rng) -> tuple[Surface, Distractor]:
    """A fixed box on the table near its centre, turned at random: the surface its top makes (its edges
    ``TOP_MARGIN`` in) and the box as the environment's "support"."""
    extents = np.array([rng.uniform(lo, hi) for lo, hi in sim.cfg.raised_extents])
    R, xy = rot_z(rng.uniform(-np.pi, np.pi)), rng.uniform(-0.05, 0.05, size=2)
    T = make_pose(R, np.array([xy[0], xy[1], extents[2] / 2]))
    body = sim.add_fixed_box(extents, T)
    top = make_pose(R, np.array([xy[0], xy[1], extents[2]]))
    surface = Surface(body, top, (extents[0] / 2 - TOP_MARGIN, extents[1] / 2 - TOP_MARGIN))
    return surface, Distractor("support", {"extents": extents.tolist()}, T)


def draw_shape_layout(sim: Sim, category: str, rng) -> ShapeLayout | None:
    """Place the objects of a ``category`` scene in ``sim`` (not yet settled), from ``sim.cfg.objects``. None
    when one of them finds no place."""
    surface, environment = _table(sim), []
    if category == "raised":
        surface, support = _raised_box(sim, rng)
        environment = [support]
    layout: list[Placed] = []
    for item, rel, parent in draw_plan(category, rng, sim.cfg.objects, sim.cfg):
        body = sim.add_item(item, PARKED, pieces=True)
        for _ in range(PLACE_TRIES):
            T = _place(sim, rng, layout, item, body, rel, parent, surface)
            if T is not None:
                break
        else:
            return None
        layout.append(Placed(item, T, rel, parent, body))
    return ShapeLayout(layout, surface, environment, np.array([p.T[2, :3] for p in layout]))


def _place(sim: Sim, rng, layout: list[Placed], item: MeshItem, body: int, rel: str, parent: int,
           surface: Surface) -> np.ndarray | None:
    """One try at placing ``item`` (body ``body``) by ``rel`` against ``layout[parent]``: T_world_obj, or None
    when it finds no place, ends beyond the surface's edges or touches an object besides its partner (a relation
    not drawn)."""
    if rel == "lie":
        T = place_free(sim, rng, layout, item, body, surface, sim.cfg.free_clearance)
    elif rel == "touch":
        T = place_against(sim, rng, layout[parent], item, body, surface)
    else:
        T = place_lean(sim, rng, layout[parent], item, body, surface)
    if T is None or not surface.holds(posed_points(item, T)[:, :2]):
        return None
    others = [p for j, p in enumerate(layout) if j != parent]
    return T if clear_of(sim, body, others, 2 * sim.cfg.contact_tol) else None


def holds(sim: Sim, scene: ShapeLayout) -> bool:
    """After settling: does every object rest on its surface (a raised box's objects off the table), touching
    exactly the objects it was placed against, in the stable pose it was placed in (within ``STABLE_TOL``: not a
    bowl tipped onto its rim by a box leaning on it), a leaning box tilted ``slant_range`` degrees?"""
    layout, surface = scene.layout, scene.surface
    planned = {(i, p.parent) for i, p in enumerate(layout) if p.parent >= 0}
    planned |= {(j, i) for i, j in planned}
    for i, p in enumerate(layout):
        if not (surface.holds(p.T[:2, 3]) and sim.touching(p.body, surface.body)):
            return False
        tipped = np.degrees(np.arccos(np.clip(p.T[2, :3] @ scene.placed_up[i], -1.0, 1.0)))
        if p.relation != "lean" and tipped > STABLE_TOL:
            return False
        if surface.body != sim.table and sim.touching(p.body, sim.table):
            return False
        if any(sim.touching(p.body, q.body) != ((i, j) in planned) for j, q in enumerate(layout) if j != i):
            return False
        if p.relation == "lean":
            tilt = tilt_deg(p.T[:3, :3] @ box_frame(p.item)[0][:3, :3])
            if not sim.cfg.slant_range[0] <= tilt <= sim.cfg.slant_range[1]:
                return False
    return True
