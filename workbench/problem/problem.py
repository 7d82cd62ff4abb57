"""The estimation problem: everything a particle evaluation needs, built once per frame and picklable, so worker
processes can be started from it.

The observation is cropped to a region of interest around the objects and reduced to at most
``ProblemConfig.max_render_pixels``; hypotheses are rendered on exactly that pixel grid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from workbench.errors import InputError, check_count
from workbench.geometry import backproject, invert_pose, transform_points
from workbench.physics import PhysicsConfig
from workbench.problem.scene import Camera, Frame, ObjectModel, Table
from workbench.render.depth import RenderConfig
from workbench.render.likelihood import LikelihoodConfig, clutter_segments

# Upper bounds of the physics and render settings a user (or a session file) may give: beyond them a step never ends
# (a simulation that may run 10**30 steps) or pybullet and OpenGL overflow their C integers.
PHYSICS_MAX = {"timestep": 0.1, "solver_iterations": 10_000, "max_steps": 100_000, "check_every": 10_000,
               "rest_checks": 10_000, "separation_iterations": 10_000, "rest_linear": 100.0, "rest_angular": 1000.0,
               "table_thickness": 10.0, "max_speed": 1e4, "max_angular": 1e5, "max_distance": 1e3,
               "penetration_tolerance": 1.0, "gravity": 1e3, "table_friction": 100.0}
RENDER_BACKENDS = ("auto", "osmesa", "egl")
MAX_FRAMEBUFFER = 16384
MAX_RENDER_PIXELS = 25_000_000  # a hypothesis rendered finer than the largest depth image read (io.bop) adds nothing


@dataclass(frozen=True)
class ProblemConfig:
    max_render_pixels: int = 160 * 120
    # Small objects get the pixels they need: the grid is made finer (up to 2x max_render_pixels) until the
    # smallest object covers about this many pixels at the objects' median depth.
    min_object_pixels: int = 300
    # A scene with an object resting more than this (m) outside the object region (``Table.region_*``, where
    # something stands on the table) is ruled out: no object is seen there. The table itself may go on out of view
    # (``support``), and without this prior the search parks objects it cannot place on unmodelled clutter or at
    # the image's edges. An object hidden behind what the region shows may rest beyond it
    # (``evaluation.hidden_behind_region``).
    region_margin: float = 0.05
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    likelihood: LikelihoodConfig = field(default_factory=LikelihoodConfig)
    render: RenderConfig = field(default_factory=RenderConfig)

    def validate(self, where: str = "") -> None:
        """What ``build_problem`` would refuse only after the frame is loaded, and the bounds of the physics and
        render settings (``PhysicsConfig`` checks only their signs): InputError naming the setting, its name
        prefixed by ``where`` (e.g. ``problem_config.`` in a session file)."""
        self.likelihood.validate()
        lik = self.likelihood
        for name in ("sigma", "depth_range", "max_residual"):  # metres; squared and divided by, so not too small
            value = getattr(lik, name)
            if not (isinstance(value, (int, float)) and 1e-6 <= value <= 1e3):
                raise InputError(f"{where}likelihood.{name}", f"must be from 1e-6 to 1000 metres, got {value!r}")
        check_count(self.max_render_pixels, f"{where}max_render_pixels" if where else "--max-render-pixels", low=64,
                    high=MAX_RENDER_PIXELS)
        check_count(self.min_object_pixels, f"{where}min_object_pixels", low=0)
        for name, high in PHYSICS_MAX.items():
            value = getattr(self.physics, name)
            if not value <= high:
                raise InputError(f"{where}physics.{name}", f"must be at most {high:g}, got {value!r}")
        if not self.physics.off_table_z >= -1e3:
            raise InputError(f"{where}physics.off_table_z", f"must be at least -1000, got {self.physics.off_table_z!r}")
        if self.render.backend not in RENDER_BACKENDS:
            raise InputError(f"{where}render.backend", f"must be one of {', '.join(RENDER_BACKENDS)}, got "
                                                       f"{self.render.backend!r}")
        check_count(self.render.max_framebuffer, f"{where}render.max_framebuffer", low=64, high=MAX_FRAMEBUFFER)


# Readings at least this high (m) above the table are objects, not table noise, when telling what hides what.
HIDER_HEIGHT = 0.01


@dataclass
class Problem:
    """``camera``: full-resolution camera with ``T_cam_world``; ``roi``: (x0, y0, w, h) of the full image;
    ``render_camera``: the cropped, scaled camera hypotheses are rendered with; ``observed`` and ``background``:
    (h, w) float32 observed depth and table-plane depth on that grid (0 = none)."""

    camera: Camera
    table: Table
    models: list[ObjectModel]
    roi: tuple[int, int, int, int]
    render_camera: Camera
    observed: np.ndarray
    background: np.ndarray
    config: ProblemConfig

    @property
    def n_objects(self) -> int:
        return len(self.models)

    @cached_property
    def clutter(self) -> np.ndarray | None:
        """(h, w) int32: the observation's pieces of possible clutter (``clutter_segments``), found once; None when
        the likelihood has no clutter floor, which alone reads them."""
        likelihood = self.config.likelihood
        return clutter_segments(self.observed, self.background, likelihood) if likelihood.floored else None

    @cached_property
    def hiders(self) -> np.ndarray:
        """(h, w) bool on the render grid: the readings that stand at least ``HIDER_HEIGHT`` above the table within
        ``region_margin`` of the object region, i.e. what the objects seen there show. Only these can hide an object
        that rests beyond the region (``evaluation.hidden_behind_region``); clutter beyond it hides nothing, or any
        object laid over clutter would count as hidden by it."""
        world = transform_points(invert_pose(self.camera.T_cam_world), backproject(self.observed, self.render_camera.K))
        lo = np.asarray(self.table.region_min) - self.config.region_margin
        hi = np.asarray(self.table.region_max) + self.config.region_margin
        inside = np.all((world[..., :2] >= lo) & (world[..., :2] <= hi), axis=-1)
        return (self.observed > 0) & (world[..., 2] >= HIDER_HEIGHT) & inside


def region_of_interest(camera: Camera, table: Table, models: list[ObjectModel]) -> tuple[int, int, int, int]:
    """(x0, y0, w, h): the image rectangle in which any object resting in the table's object region can appear."""
    # The region bounds the points seen above the table; an object may reach beyond it by part of its size
    # (unseen sides, hidden objects), and stand up to its largest extent tall.
    size = max(float(np.max(m.mesh.extents)) for m in models)
    margin = 0.5 * size
    (x_lo, y_lo), (x_hi, y_hi) = table.region_min, table.region_max
    xs = [x_lo - margin, x_hi + margin]
    ys = [y_lo - margin, y_hi + margin]
    corners = np.array([[x, y, z] for x in xs for y in ys for z in (0.0, size)])
    p = transform_points(camera.T_cam_world, corners)
    p = p[p[:, 2] > 1e-3]
    if len(p) == 0:
        raise InputError(None, "the objects' region lies behind the camera: check the camera pose")
    uv = p[:, :2] / p[:, 2:3] @ camera.K[:2, :2].T + camera.K[:2, 2]
    x0 = int(np.clip(np.floor(uv[:, 0].min()), 0, camera.width - 1))
    y0 = int(np.clip(np.floor(uv[:, 1].min()), 0, camera.height - 1))
    x1 = int(np.clip(np.ceil(uv[:, 0].max()) + 1, x0 + 1, camera.width))
    y1 = int(np.clip(np.ceil(uv[:, 1].max()) + 1, y0 + 1, camera.height))
    return x0, y0, x1 - x0, y1 - y0


def sample_grid(image: np.ndarray, roi: tuple[int, int, int, int], scale: float) -> np.ndarray:
    """Nearest-pixel sample of ``image`` (H, W) on the grid of ``Camera.cropped(*roi).scaled(scale)`` -> (h, w).

    Nearest (not averaging) keeps holes holes and never invents depths between an object and the table."""
    x0, y0, w, h = roi
    out_w, out_h = int(round(w * scale)), int(round(h * scale))
    u = np.clip(np.round((np.arange(out_w) + 0.5) / scale - 0.5).astype(int), 0, w - 1) + x0
    v = np.clip(np.round((np.arange(out_h) + 0.5) / scale - 0.5).astype(int), 0, h - 1) + y0
    return image[np.ix_(v, u)]


def table_depth(camera: Camera, table: Table) -> np.ndarray:
    """Camera-z depth of the table top at every pixel of ``camera`` -> (H, W) float32, 0 off the table."""
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(camera.K).T  # (H, W, 3), z = 1
    T_world_cam = invert_pose(camera.T_cam_world)
    origin = T_world_cam[:3, 3]
    dirs = rays @ T_world_cam[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -origin[2] / dirs[..., 2]  # ray parameter where world z = 0; equals camera depth since ray z = 1
    hit = origin[None, None, :2] + s[..., None] * dirs[..., :2]
    on_table = (
        (s > 0)
        & (hit[..., 0] >= table.x_min) & (hit[..., 0] <= table.x_max)
        & (hit[..., 1] >= table.y_min) & (hit[..., 1] <= table.y_max)
    )
    return np.where(on_table, s, 0.0).astype(np.float32)


def render_scale(depth: np.ndarray, camera: Camera, roi: tuple[int, int, int, int], models: list[ObjectModel],
                 config: ProblemConfig) -> float:
    """The factor (<= 1) from the full image to the render grid: ``max_render_pixels`` over the ROI, raised (up to
    2x the pixels) so that the smallest object covers ``min_object_pixels`` at the median depth of the ROI."""
    x0, y0, w, h = roi
    scale = min(1.0, float(np.sqrt(config.max_render_pixels / (w * h))))
    window = depth[y0:y0 + h, x0:x0 + w]
    z = float(np.median(window[window > 0])) if np.any(window > 0) else 0.0
    if z <= 0 or config.min_object_pixels <= 0:
        return scale
    # The smallest object's typical silhouette: the middle one of its three face areas (m^2), in full-res pixels.
    area = min(float(np.median([e[0] * e[1], e[1] * e[2], e[0] * e[2]])) for e in (m.mesh.extents for m in models))
    pixels = camera.K[0, 0] * camera.K[1, 1] * area / (z * z)
    wanted = float(np.sqrt(config.min_object_pixels / max(pixels, 1e-9)))
    cap = float(np.sqrt(2.0 * config.max_render_pixels / (w * h)))
    return min(1.0, max(scale, min(wanted, cap)))


def build_problem(
    frame: Frame, models: list[ObjectModel], camera: Camera, table: Table, config: ProblemConfig = ProblemConfig()
) -> Problem:
    """Assemble the problem from a frame whose support surface is known (``camera.T_cam_world`` set)."""
    config.likelihood.validate()
    if camera.T_cam_world is None:
        raise InputError(frame.source, "the table pose is unknown: estimate the support surface first")
    if config.max_render_pixels < 64:
        raise InputError("max_render_pixels", f"at least 64 pixels are needed, got {config.max_render_pixels}")
    roi = region_of_interest(camera, table, models)
    scale = render_scale(frame.depth, camera, roi, models, config)
    render_camera = camera.cropped(*roi).scaled(scale)
    return Problem(
        camera=camera,
        table=table,
        models=models,
        roi=roi,
        render_camera=render_camera,
        observed=sample_grid(frame.depth, roi, scale).astype(np.float32),
        background=table_depth(render_camera, table),
        config=config,
    )
