"""Distractors: things on the desk the estimator is not told about (books, cups, bottles, cables, and with given
models other models in one of their stable poses), placed after the objects have settled, resting on the desk and
clear of the objects. A raised box the objects rest on (``support``) is listed with them: it is in the depth, not
in scene_gt.json."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from workbench.geometry import make_pose, rot_z
from workbench.synth.config import SynthConfig
from workbench.synth.layout import Placed
from workbench.synth.meshes import can_mesh, tube_mesh
from workbench.synth.objects import Item, box_mesh, item_mesh, lying_rotation


@dataclass
class Distractor:
    """A slab (book, notepad), a cylinder (cup, bottle) or a cable lying on the table, a given model (``item``)
    or the raised box objects rest on (support).

    ``params`` (metres): slab and support {"extents"}, cylinder {"radius", "height"}, cable {"radius", "path"
    (P, 3) in the model frame}, model {}. ``T``: (4, 4) T_world_obj, the model resting on z = 0."""

    kind: str
    params: dict
    T: np.ndarray
    item: Item | None = None  # the model of a "model" distractor

    def mesh(self) -> trimesh.Trimesh:
        """Model-frame mesh (metres)."""
        return item_mesh(self.item) if self.item is not None else distractor_mesh(self.kind, self.params)


DISTRACTOR_KINDS = ("slab", "cylinder", "cable")


def distractor_mesh(kind: str, params: dict) -> trimesh.Trimesh:
    """A distractor's mesh in its model frame (centred; the cable along its path). Metres. Not for a model."""
    if kind in ("slab", "support"):
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


def _draw_placed(rng, centre: np.ndarray, models: tuple[Item, ...]):
    """One distractor 10-45 cm from ``centre`` (2,) on the table: (kind, params, model-frame mesh, T_world_obj,
    the model or None). A model, half the time where ``models`` are given, lies in one of its stable poses."""
    item = models[int(rng.integers(len(models)))] if models and rng.random() < 0.5 else None
    if item is None:
        kind, params = draw_distractor(rng)
        mesh = distractor_mesh(kind, params)
    else:
        kind, params, mesh = "model", {}, item_mesh(item)
        R = lying_rotation(item, rng)
    a, r = rng.uniform(-np.pi, np.pi), rng.uniform(0.10, 0.45)
    xy = centre + r * np.array([np.cos(a), np.sin(a)])
    if item is None:
        T = make_pose(rot_z(rng.uniform(-np.pi, np.pi)), np.array([xy[0], xy[1], -mesh.bounds[0, 2]]))
    else:
        T = make_pose(R, np.array([xy[0], xy[1], -np.min(mesh.vertices @ R[2])]))
    return kind, params, mesh, T, item


def place_distractors(rng, layout: list[Placed], count: int, cfg: SynthConfig, models: tuple[Item, ...] = (),
                      obstacles: tuple[trimesh.Trimesh, ...] = ()) -> list[Distractor]:
    """Up to ``count`` distractors resting on the table 10-45 cm from the objects' centre, each at least
    ``cfg.distractor_clearance`` (seen from above) from every object and from ``obstacles`` (world meshes: a
    raised box), so that no relation changes, and clear of one another and of the table's edge. Half of them,
    where ``models`` are given, are one of those in a stable pose. Static: they rest on the table by
    construction."""
    objects = np.concatenate([_footprint(item_mesh(p.item).apply_transform(p.T)) for p in layout])
    tree = cKDTree(np.concatenate([objects] + [_footprint(m, 4000) for m in obstacles]))  # a large box: dense
    centre = objects.mean(axis=0)
    half = np.array(cfg.table_size) / 2 - 0.02
    placed, taken = [], np.zeros((0, 2))
    for _ in range(count):
        for _ in range(30):
            kind, params, mesh, T, item = _draw_placed(rng, centre, models)
            pts = _footprint(mesh.apply_transform(T))
            if np.any(np.abs(pts) > half) or tree.query(pts)[0].min() < cfg.distractor_clearance:
                continue
            if len(taken) and cKDTree(taken).query(pts)[0].min() < 0.01:
                continue
            placed.append(Distractor(kind, params, T, item))
            taken = np.concatenate([taken, pts])
            if item is not None:
                models = tuple(m for m in models if m is not item)  # each model once
            break
    return placed
