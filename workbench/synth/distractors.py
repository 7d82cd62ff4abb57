"""Distractors: things on the desk the estimator is not told about (books, cups, bottles, cables), placed after
the objects have settled, resting on the desk and clear of the objects."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from workbench.geometry import make_pose, rot_z
from workbench.synth.config import SynthConfig
from workbench.synth.layout import Placed
from workbench.synth.meshes import can_mesh, tube_mesh
from workbench.synth.objects import box_mesh, item_mesh


@dataclass
class Distractor:
    """A slab (book, notepad), a cylinder (cup, bottle) or a cable lying on the table.

    ``params`` (metres): slab {"extents"}, cylinder {"radius", "height"}, cable {"radius", "path" (P, 3) in the
    model frame}. ``T``: (4, 4) T_world_obj, the model resting on z = 0."""

    kind: str
    params: dict
    T: np.ndarray

    def mesh(self) -> trimesh.Trimesh:
        """Model-frame mesh (metres)."""
        return distractor_mesh(self.kind, self.params)


DISTRACTOR_KINDS = ("slab", "cylinder", "cable")


def distractor_mesh(kind: str, params: dict) -> trimesh.Trimesh:
    """A distractor's mesh in its model frame (centred; the cable along its path). Metres."""
    if kind == "slab":
        return box_mesh(params["extents"])
    if kind == "cylinder":
        return can_mesh(params["radius"], params["height"], sections=32)
    return tube_mesh(np.asarray(params["path"]), params["radius"])


def draw_distractor(rng) -> tuple[str, dict]:
    """The shape of one distractor: sizes of books, cups and bottles, cables 25-70 cm long."""
    kind = DISTRACTOR_KINDS[int(rng.integers(len(DISTRACTOR_KINDS)))]
    if kind == "slab":
        return kind, {"extents": [rng.uniform(0.10, 0.30), rng.uniform(0.07, 0.22), rng.uniform(0.004, 0.04)]}
    if kind == "cylinder":
        return kind, {"radius": rng.uniform(0.015, 0.045), "height": rng.uniform(0.03, 0.22)}
    radius, steps = rng.uniform(0.002, 0.005), int(rng.uniform(25, 70))
    heading = np.cumsum(rng.normal(0.0, 0.15, size=steps)) + rng.uniform(-np.pi, np.pi)  # 1 cm steps, bending
    path = np.cumsum(0.01 * np.stack([np.cos(heading), np.sin(heading), np.zeros(steps)], axis=-1), axis=0)
    return kind, {"radius": radius, "path": (path - path.mean(axis=0)).tolist()}


def _footprint(mesh_world: trimesh.Trimesh, n: int = 400) -> np.ndarray:
    """Points covering a posed mesh, seen from above: vertices and surface samples, xy. -> (N, 2)."""
    samples, _ = trimesh.sample.sample_surface(mesh_world, n, seed=0)
    return np.concatenate([np.asarray(mesh_world.vertices), samples])[:, :2]


def place_distractors(rng, layout: list[Placed], count: int, cfg: SynthConfig) -> list[Distractor]:
    """Up to ``count`` distractors resting on the table 10-45 cm from the objects' centre, each at least
    ``cfg.distractor_clearance`` (seen from above) from every object, so that no relation changes, and clear of
    one another and of the table's edge. Static: they rest on the table by construction."""
    objects = np.concatenate([_footprint(item_mesh(p.item).apply_transform(p.T)) for p in layout])
    tree = cKDTree(objects)
    centre = objects.mean(axis=0)
    half = np.array(cfg.table_size) / 2 - 0.02
    placed, taken = [], np.zeros((0, 2))
    for _ in range(count):
        for _ in range(30):
            kind, params = draw_distractor(rng)
            mesh = distractor_mesh(kind, params)
            a, r = rng.uniform(-np.pi, np.pi), rng.uniform(0.10, 0.45)
            xy = centre + r * np.array([np.cos(a), np.sin(a)])
            T = make_pose(rot_z(rng.uniform(-np.pi, np.pi)), np.array([xy[0], xy[1], -mesh.bounds[0, 2]]))
            pts = _footprint(mesh.apply_transform(T))
            if np.any(np.abs(pts) > half) or tree.query(pts)[0].min() < cfg.distractor_clearance:
                continue
            if len(taken) and cKDTree(taken).query(pts)[0].min() < 0.01:
                continue
            placed.append(Distractor(kind, params, T))
            taken = np.concatenate([taken, pts])
            break
    return placed
