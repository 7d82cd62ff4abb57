"""One generated scene: layouts are drawn until one settles into what its category says, distractors are placed,
and a camera is drawn until it shows the scene so; its depth is degraded by the sensor model."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from workbench.synth.config import DESKS, HANDLE_CATEGORIES, SHAPE_CATEGORIES, DeskSpec, SynthConfig
from workbench.synth.distractors import Distractor, place_distractors
from workbench.synth.layout import Placed, draw_layout, relations_hold, settle_layout
from workbench.synth.objects import item_mesh
from workbench.synth.sensor.model import apply_sensor
from workbench.synth.shape_layouts import draw_shape_layout, holds
from workbench.synth.sim import Sim
from workbench.synth.views import (
    draw_camera,
    draw_handle_camera,
    handle_pixels,
    in_view,
    masks_alone,
    render_clean,
)


def _bbox(mask: np.ndarray) -> list[int]:
    """BOP bbox [x, y, w, h] of a mask; [-1, -1, 0, 0] when empty (as bop_toolkit)."""
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return [-1, -1, 0, 0]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]


@dataclass
class SceneSample:
    """One generated scene. Masks (K, H, W) follow ``layout``; depths (H, W) float32 metres."""

    category: str
    layout: list[Placed]
    T_cam_world: np.ndarray
    clean_depth: np.ndarray
    depth: np.ndarray
    mask_visib: np.ndarray
    mask_all: np.ndarray
    tries: int
    distractors: list[Distractor] = field(default_factory=list)
    table_pose: bool = True  # whether scene_camera.json gives the table pose
    table_size: tuple[float, float] = SynthConfig.table_size

    @property
    def visib_fract(self) -> np.ndarray:
        """(K,) visible pixels / pixels of the object rendered alone."""
        alone = self.mask_all.sum(axis=(1, 2))
        return np.where(alone > 0, self.mask_visib.sum(axis=(1, 2)) / np.maximum(alone, 1), 0.0)

    def gt_info(self) -> list[dict]:
        """scene_gt_info.json entries (bop_toolkit's fields)."""
        info = []
        for k in range(len(self.layout)):
            visib, alone = self.mask_visib[k], self.mask_all[k]
            info.append({
                "bbox_obj": _bbox(alone),
                "bbox_visib": _bbox(visib),
                "px_count_all": int(alone.sum()),
                "px_count_valid": int((alone & (self.depth > 0)).sum()),
                "px_count_visib": int(visib.sum()),
                "visib_fract": float(self.visib_fract[k]),
            })
        return info


def _views_ok(cfg: SynthConfig, layout: list[Placed], visib: np.ndarray) -> bool:
    hidden = np.array([p.relation == "hide" for p in layout])
    return bool(np.all(visib[hidden] < cfg.hidden_max_visib) and np.all(visib[~hidden] >= cfg.shown_min_visib))


def _handle_ok(cfg: SynthConfig, category: str, T_cam_world: np.ndarray, mug: Placed, clean: np.ndarray,
               shows: np.ndarray) -> bool:
    """Does the view hide the mug's handle (``handle_hidden``) or show it (``handle_shown``), as its category says?
    Always true for other categories."""
    if category not in HANDLE_CATEGORIES:
        return True
    n = handle_pixels(cfg, T_cam_world, mug, clean, shows)
    area = (cfg.width / 640.0) ** 2  # the thresholds are for 640 pixels wide
    return n <= cfg.handle_max_hidden_px if category == "handle_hidden" else n >= cfg.handle_min_shown_px * area


def _draw_desk(desk: DeskSpec, cfg: SynthConfig, rng) -> SynthConfig:
    """The scene's configuration with its table size drawn (``cfg`` itself when the desk keeps the default)."""
    if desk.table_size is None:
        return cfg
    (x0, x1), (y0, y1) = desk.table_size
    return replace(cfg, table_size=(float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1))))


def _settled_layout(sim: Sim, category: str, rng) -> tuple[list[Placed], list[np.ndarray], list[Distractor]] | None:
    """One layout of ``category`` drawn and settled: (objects, normals of the faces hidden behind, the
    environment: a raised box), or None when it did not settle into what the category says."""
    if category in SHAPE_CATEGORIES:
        shaped = draw_shape_layout(sim, category, rng)
        if shaped is None or not (settle_layout(sim, shaped.layout) and holds(sim, shaped)):
            return None
        return shaped.layout, [], shaped.environment
    drawn = draw_layout(sim, category, rng)
    if drawn is None:
        return None
    layout, hide_normals = drawn
    if not (settle_layout(sim, layout) and relations_hold(sim, layout)):
        return None
    return layout, hide_normals, []


def _distractors(rng, category: str, layout: list[Placed], environment: list[Distractor], count: int,
                 cfg: SynthConfig) -> list[Distractor]:
    """The environment and ``count`` distractors on the desk; with real shapes, some of them models not in the
    scene."""
    if category not in SHAPE_CATEGORIES:
        return place_distractors(rng, layout, count, cfg) if count else []
    listed = {id(p.item) for p in layout}
    spare = tuple(o for o in cfg.objects if id(o) not in listed)
    obstacles = tuple(d.mesh().apply_transform(d.T) for d in environment)
    return environment + (place_distractors(rng, layout, count, cfg, spare, obstacles) if count else [])


def generate_scene(sim: Sim, category: str, rng: np.random.Generator, cfg: SynthConfig,
                   desk: DeskSpec | None = None) -> SceneSample:
    """Draw layouts until one settles into what ``category`` says and a camera shows it so. ``desk``: table size,
    distractors and table pose (default: the category's, ``DESKS``)."""
    desk = DESKS.get(category, DeskSpec()) if desk is None else desk
    cfg = _draw_desk(desk, cfg, rng)
    sim.cfg = cfg
    K = cfg.K()
    for tries in range(1, cfg.max_layout_tries + 1):
        sim.reset()
        settled = _settled_layout(sim, category, rng)
        if settled is None:
            continue
        layout, hide_normals, environment = settled
        lo, hi = desk.distractors
        distractors = _distractors(rng, category, layout, environment, int(rng.integers(lo, hi + 1)) if hi > 0 else 0,
                                   cfg)
        for _ in range(cfg.max_camera_tries):
            T_cam_world = (draw_handle_camera(cfg, rng, layout, category == "handle_hidden")
                           if category in HANDLE_CATEGORIES else draw_camera(cfg, rng, layout, hide_normals))
            if not in_view(cfg, T_cam_world, layout):
                continue
            clean, idx = render_clean(cfg, T_cam_world, layout, distractors)
            mask_visib = idx[None] == np.arange(len(layout))[:, None, None]
            cam_meshes = [item_mesh(p.item).apply_transform(T_cam_world @ p.T) for p in layout]
            mask_all = masks_alone(K, cfg.width, cfg.height, cam_meshes)
            alone = mask_all.sum(axis=(1, 2))
            visib = mask_visib.sum(axis=(1, 2)) / np.maximum(alone, 1)
            if not (_views_ok(cfg, layout, visib) and _handle_ok(cfg, category, T_cam_world, layout[0], clean,
                                                                  mask_visib[0])):
                continue
            depth = apply_sensor(clean, rng, cfg.sensor, K)
            table_pose = bool(rng.random() < desk.table_pose) if 0.0 < desk.table_pose < 1.0 else desk.table_pose >= 1
            return SceneSample(category, layout, T_cam_world, clean, depth, mask_visib, mask_all, tries,
                               distractors, table_pose, cfg.table_size)
    raise RuntimeError(f"no valid {category!r} scene in {cfg.max_layout_tries} layouts; loosen SynthConfig")
