"""Placing given models (``bodies``: their V-HACD pieces) on a surface, the table's top or a raised box's: free
in one of their stable poses, slid against another object until they touch, or (a box) leaning on one. Each new
object is moved along one degree of freedom to its first contact with its partner, as ``layout`` places the
built-in objects."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.geometry import make_pose, rot_z
from workbench.synth.bodies import piece_body, piece_rotations
from workbench.synth.layout import Placed
from workbench.synth.objects import EZ, MeshItem
from workbench.synth.roles import box_frame
from workbench.synth.sim import Sim, bisect_contact


@dataclass(frozen=True)
class Surface:
    """What objects rest on: the table's top or a raised box's. ``T`` (4, 4): T_world_top, the top's centre with
    z up; ``half`` (2,): how far from that centre along the top's x and y objects may stand (half its sizes, less
    a margin), m; ``body``: its body in the sim."""

    body: int
    T: np.ndarray
    half: tuple[float, float]

    @property
    def z(self) -> float:
        return float(self.T[2, 3])

    def holds(self, xy: np.ndarray) -> bool:
        """Are the world points ``xy`` (N, 2) all within the top's edges (``half``)?"""
        local = (np.atleast_2d(xy) - self.T[:2, 3]) @ self.T[:2, :2]
        return bool(np.all(np.abs(local) <= np.asarray(self.half)))


def posed_points(item: MeshItem, T: np.ndarray) -> np.ndarray:
    """The body's piece vertices at T_world_obj (4, 4), world frame. -> (N, 3)"""
    return piece_body(item).points @ T[:3, :3].T + T[:3, 3]


def reach(item: MeshItem, R: np.ndarray, direction: np.ndarray) -> float:
    """How far the body with rotation R (3, 3) extends from its origin along a unit world direction (3,)."""
    return float(np.max(piece_body(item).points @ (R.T @ direction)))


def stable_rotation(item: MeshItem, rng) -> np.ndarray:
    """One of the body's stable rotations, drawn by how likely it lands in it, at a random heading. -> (3, 3)"""
    R, p = piece_rotations(item)
    return rot_z(rng.uniform(-np.pi, np.pi)) @ R[rng.choice(len(p), p=p)]


def resting_pose(item: MeshItem, R: np.ndarray, xy: np.ndarray, surface: Surface, lift: float) -> np.ndarray:
    """T_world_obj (4, 4) with rotation R, its centre over ``xy`` (2,), its lowest point ``lift`` m above the
    surface."""
    return make_pose(R, np.array([xy[0], xy[1], surface.z + reach(item, R, -EZ) + lift]))


def clear_of(sim: Sim, body: int, others: list[Placed], gap: float) -> bool:
    """Is ``body`` more than ``gap`` m from every one of ``others``?"""
    return all(sim.distance(body, p.body) > gap for p in others)


def place_free(sim: Sim, rng, layout: list[Placed], item: MeshItem, body: int, surface: Surface,
               clearance: float) -> np.ndarray | None:
    """``item`` in a stable pose on ``surface``, within its edges and ``clearance`` m clear of every placed
    object: tried at 40 spots on rings 6-45 cm about the layout's centre (the surface's, for
    the first object), nearest first, so that the objects stand close as on a desk. -> T_world_obj or None."""
    centre = np.mean([p.T[:2, 3] for p in layout], axis=0) if layout else surface.T[:2, 3]
    for k in range(40):
        R = stable_rotation(item, rng)
        a, r = rng.uniform(-np.pi, np.pi), (0.06 + 0.01 * k if layout else 0.005 * k)
        T = resting_pose(item, R, centre + r * np.array([np.cos(a), np.sin(a)]), surface, sim.cfg.lift)
        if not surface.holds(posed_points(item, T)[:, :2]):
            continue
        sim.set_pose(body, T)
        if clear_of(sim, body, layout, clearance):
            return T
    return None


def first_contact(sim: Sim, body: int, partner: int, pose_at, s_free: float, s_end: float,
                  steps: int) -> np.ndarray | None:
    """Move ``body`` along ``pose_at(s) -> (4, 4)`` from ``s_free`` towards ``s_end`` to where it first touches
    ``partner``: the first of ``steps`` even steps that overlaps it, then bisection back to the step before (as
    sliding it in would meet it; a concave partner may be touched again further on). None when it starts
    overlapping or never touches."""
    s = np.linspace(s_free, s_end, steps + 1)
    sim.set_pose(body, pose_at(s[0]))
    if sim.distance(body, partner) <= 0:
        return None
    for a, b in zip(s[:-1], s[1:]):
        sim.set_pose(body, pose_at(b))
        if sim.distance(body, partner) <= 0:
            return bisect_contact(sim, body, partner, pose_at, a, b)
    return None


def place_against(sim: Sim, rng, parent: Placed, item: MeshItem, body: int, surface: Surface) -> np.ndarray | None:
    """``item`` in a stable pose on ``surface``, slid towards ``parent`` along a random level direction (aimed
    up to a third of the parent's width off its centre) until it touches it. -> T_world_obj or None."""
    R = stable_rotation(item, rng)
    a = rng.uniform(-np.pi, np.pi)
    n, t = np.array([np.cos(a), np.sin(a), 0.0]), np.array([-np.sin(a), np.cos(a), 0.0])
    size = np.max(np.linalg.norm(piece_body(parent.item).points, axis=1))
    far = size + np.max(np.linalg.norm(piece_body(item).points, axis=1)) + 0.02
    xy = parent.T[:2, 3] + t[:2] * rng.uniform(-1, 1) * size / 3

    def pose_at(s: float) -> np.ndarray:
        return resting_pose(item, R, xy + n[:2] * s, surface, sim.cfg.lift)

    return first_contact(sim, body, parent.body, pose_at, far, 0.0, int(far / 0.004))


def place_lean(sim: Sim, rng, parent: Placed, item: MeshItem, body: int, surface: Surface) -> np.ndarray | None:
    """Box ``item`` standing on its bottom edge on the surface beside ``parent`` (its longest side up, its
    thinnest towards the parent), tipped over onto it until they touch: 15-45 degrees from upright where it meets
    the parent's side, further where it meets a low parent's top (an upturned bowl). -> T_world_obj or None."""
    T_obj_box, e = box_frame(item)
    long, thin = int(np.argmax(e)), int(np.argmin(e))
    wide = 3 - long - thin
    a = rng.uniform(-np.pi, np.pi)
    n, t = np.array([np.cos(a), np.sin(a), 0.0]), np.array([-np.sin(a), np.cos(a), 0.0])
    R0 = np.zeros((3, 3))
    R0[:, long], R0[:, thin], R0[:, wide] = EZ, n, t
    if np.linalg.det(R0) < 0:
        R0[:, wide] = -t
    h = e[long]
    R_A = parent.T[:3, :3]
    top = parent.T[2, 3] + reach(parent.item, R_A, EZ) - surface.z
    theta = np.radians(rng.uniform(15.0, 45.0))
    # From the parent's side: where the top edge meets it when the parent is taller than the leaning box's top,
    # else where the leaning face meets the parent's top.
    D = h * np.sin(theta) if h * np.cos(theta) <= top else top * np.tan(theta)
    pivot = parent.T[:3, 3] + n * (reach(parent.item, R_A, n) + D)
    pivot += t * rng.uniform(-0.3, 0.3) * reach(parent.item, R_A, t)
    pivot[2] = surface.z + sim.cfg.lift
    c0 = pivot + n * e[thin] / 2 + EZ * h / 2
    k = np.cross(n, EZ)  # turning about k carries the top towards the parent
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    T_box_obj = np.linalg.inv(T_obj_box)

    def pose_at(angle: float) -> np.ndarray:
        Rk = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
        return make_pose(Rk @ R0, pivot + Rk @ (c0 - pivot)) @ T_box_obj

    return first_contact(sim, body, parent.body, pose_at, 0.0, np.radians(85.0), 85)
