"""The 3D scene: the observation, the particle cloud, the chosen particle before/after physics, the heatmap.

This module is the viser edge: poses arrive as 4x4 table-frame matrices and leave as viser's (wxyz, position).
Each layer creates its nodes once per loaded frame and afterwards only moves, recolours or hides them, so an
iteration costs a few small messages, not a re-upload of the meshes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import viser

from workbench.app.protocol import Chosen, MeshData, ObservationView, ParticleCloud, PointSet
from workbench.app.ui.widgets import colors

SCENE_MODES = ("after physics", "before physics", "before + after", "side by side", "hidden")
HEATMAP_MODES = ("log-likelihood", "residual", "off")
# No shadows anywhere: a shadow map is another pass over the scene in every frame, and software WebGL draws a frame
# at least once a second (viser's idle heartbeat), so every pass costs CPU for as long as a tab is open.
NO_SHADOW = {"cast_shadow": False, "receive_shadow": False}
AMBIENT = 1.2  # the ambient light's intensity: lights the sides the default lights (from above and below) miss


def light_cheaply(server: viser.ViserServer) -> None:
    """Light the scene without viser's default environment map or shadow maps.

    In software WebGL almost all of a frame's cost is shading pixels. Measured per draw call in headless Chromium
    (SwiftShader, 1280x800, demo frame): the table slab took ~290 ms and the 64 particle wireframes ~490 ms of every
    frame; without the lights' shadow maps (sampled by every lit pixel) the table took ~130 ms, and without the
    environment map's image-based lighting as well ~25 ms, the wireframes ~90 ms. An ambient term stands in for
    the environment's fill light."""
    server.scene.configure_environment_map(hdri=None)
    server.scene.configure_default_lights(enabled=True, cast_shadow=False)
    server.scene.add_light_ambient("/lights/ambient", intensity=AMBIENT)


def wxyz_from_matrices(R: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) -> unit quaternions (..., 4) wxyz with w >= 0, vectorised (thousands per update)."""
    R = np.asarray(R, dtype=np.float64)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    q = np.stack(
        [
            np.sqrt(np.maximum(0.0, 1.0 + m00 + m11 + m22)),
            np.sqrt(np.maximum(0.0, 1.0 + m00 - m11 - m22)),
            np.sqrt(np.maximum(0.0, 1.0 - m00 + m11 - m22)),
            np.sqrt(np.maximum(0.0, 1.0 - m00 - m11 + m22)),
        ],
        axis=-1,
    ) / 2.0
    # Magnitudes from the diagonal, signs from the antisymmetric part (relative to w >= 0). Near 180 degrees
    # w -> 0 and the antisymmetric part vanishes, so take the signs from the symmetric part against the largest.
    q[..., 1] = np.copysign(q[..., 1], R[..., 2, 1] - R[..., 1, 2])
    q[..., 2] = np.copysign(q[..., 2], R[..., 0, 2] - R[..., 2, 0])
    q[..., 3] = np.copysign(q[..., 3], R[..., 1, 0] - R[..., 0, 1])
    flip = q[..., 0] < 1e-3
    if np.any(flip):
        from workbench.geometry import matrix_to_quat_wxyz  # exact (Shepperd), slow: only for the rare few

        q[flip] = matrix_to_quat_wxyz(R[flip])
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def split_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 4, 4) -> (wxyz (..., 4), position (..., 3))."""
    return wxyz_from_matrices(T[..., :3, :3]), np.asarray(T[..., :3, 3], dtype=np.float64)


def outline_segments(mesh: MeshData) -> np.ndarray:
    """(E, 2, 3) float32 object-frame segments outlining ``mesh``: its ``edges`` (observation.outline_edges), else
    every triangle edge."""
    if mesh.edges is not None:
        return np.asarray(mesh.edges, np.float32)
    f = np.asarray(mesh.faces)
    pairs = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    return np.asarray(mesh.vertices, np.float32)[pairs]


def outline_mesh(mesh: MeshData, cloud: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``mesh``'s outline (``cloud``: the particles' coarser one, where it has one) as a mesh whose wireframe draws
    only the outline (vertices (2E, 3), faces (E, 3)): each segment a degenerate triangle (a, b, b), whose
    wireframe is the line a-b. Instanced meshes (the particles) have no line-segment form in viser."""
    seg = np.asarray(mesh.cloud_edges, np.float32) if cloud and mesh.cloud_edges is not None else \
        outline_segments(mesh)
    vertices = seg.reshape(-1, 3)
    a = np.arange(0, len(vertices), 2, dtype=np.int32)
    return vertices, np.stack([a, a + 1, a + 1], axis=1)


OUTLINE_WIDTH = 2.0  # px, the ground truth's and labels' lines


@dataclass
class Nodes:
    """Scene handles to remove together when a new frame is loaded."""

    handles: list = field(default_factory=list)

    def add(self, handle):
        self.handles.append(handle)
        return handle

    def remove(self, handle) -> None:
        """Remove one node now (and not again at ``clear``, which viser would warn about)."""
        handle.remove()
        self.handles = [h for h in self.handles if h is not handle]

    def clear(self) -> None:
        for h in self.handles:
            h.remove()
        self.handles = []


DEPTH_BINS = 4  # each cloud of observed points is drawn as this many, nearest to farthest from the sensor


def by_depth(c: PointSet, T_world_cam: np.ndarray, bins: int = DEPTH_BINS) -> list[tuple]:
    """The points of ``c`` in ``bins`` bands of depth from the sensor (pose ``T_world_cam``) -> per band (points,
    colours, point size). ``c.point_size`` fits the pixels' spacing at the median depth, and that spacing grows
    with depth: one size for all drew the near points as overlapping tiles and left gaps between the far ones."""
    if not len(c.points):
        return []
    depth = (c.points - T_world_cam[:3, 3]) @ T_world_cam[:3, 2]
    middle = max(float(np.median(depth)), 1e-6)
    band = np.searchsorted(np.quantile(depth, np.linspace(0.0, 1.0, bins + 1)[1:-1]), depth)
    return [(c.points[band == b], c.colors[band == b],
             c.point_size * max(float(np.median(depth[band == b])), 1e-6) / middle)
            for b in range(bins) if np.any(band == b)]


@dataclass
class ObservationLayer:
    """The frame as seen: point clouds (fine near the objects, coarse elsewhere), table, object region, camera
    frustum, ground truth (hidden by default)."""

    server: viser.ViserServer
    nodes: Nodes = field(default_factory=Nodes)
    clouds: list = field(default_factory=list)
    gt: list = field(default_factory=list)

    def draw(self, view: ObservationView, show_cloud: bool, show_gt: bool) -> None:
        scene, add = self.server.scene, self.nodes.add
        self.nodes.clear()
        # Square points: "rounded" ones cost a fragment-shader discard per pixel in software WebGL.
        self.clouds = [
            add(scene.add_point_cloud(f"/observation/{name}/{b}", points, rgb, point_size=size,
                                      point_shape="square", visible=show_cloud))
            for name, c in (("points", view.near), ("surroundings", view.far))
            for b, (points, rgb, size) in enumerate(by_depth(c, view.T_world_cam))
        ]
        x0, x1, y0, y1 = view.table
        # The table slab's top a millimetre below z = 0, so the table's own points stay visible on it. Toon-shaded: a
        # flat slab looks the same, and software WebGL shades each of its pixels for less.
        add(scene.add_box(
            "/observation/table", color=colors.TABLE_COLOR, dimensions=(x1 - x0, y1 - y0, 0.004),
            position=((x0 + x1) / 2, (y0 + y1) / 2, -0.003), material="toon3", **NO_SHADOW,
        ))  # opaque: a blended slab this large costs a full pass of blending; it also hides the floor below it
        rx0, rx1, ry0, ry1 = view.region
        corners = np.array([[rx0, ry0, 0], [rx1, ry0, 0], [rx1, ry1, 0], [rx0, ry1, 0]], dtype=np.float32)
        add(scene.add_line_segments(
            "/observation/region", np.stack([corners, np.roll(corners, -1, axis=0)], axis=1),
            colors=colors.REGION_COLOR, thickness=1.5, thickness_units="screen",
        ))
        w, h = view.image_size
        wxyz, pos = split_pose(view.T_world_cam)
        add(scene.add_camera_frustum(
            "/observation/camera", fov=2 * np.arctan2(h / 2, view.K[1, 1]), aspect=w / h, scale=0.1,
            thickness=1.5, thickness_units="screen", color=colors.SENSOR_COLOR, wxyz=wxyz, position=pos,
        ))
        self.gt = []
        if view.gt_T_world_obj is not None:
            # Outlines (feature edges of a coarse mesh), not every triangle edge: legible on a YCB scan, and cheap.
            for k, (mesh, T) in enumerate(zip(view.meshes, view.gt_T_world_obj)):
                if np.all(np.isfinite(T)):
                    q, t = split_pose(T)
                    self.gt.append(add(scene.add_line_segments(
                        f"/observation/ground_truth/{k}", outline_segments(mesh), colors=colors.GROUND_TRUTH_COLOR,
                        thickness=OUTLINE_WIDTH, thickness_units="screen", wxyz=q, position=t, visible=show_gt)))

    def set_visible(self, cloud: bool, gt: bool) -> None:
        for h in self.clouds:
            h.visible = cloud
        for h in self.gt:
            h.visible = gt


@dataclass
class ParticleLayer:
    """Every published particle as one instanced outline per object (``outline_mesh``), coloured (and faded) by
    normalised weight, and the most likely scene drawn solid. Outlines: solid translucent particles piled up into a
    haze over the objects, and filling them cost software WebGL most of a core; every triangle edge of a YCB scan
    was noise. Clicking an instance calls ``on_pick(rank)`` (instances are in rank order)."""

    server: viser.ViserServer
    on_pick: Callable[[int], None]
    meshes: list[MeshData] = field(default_factory=list)
    batches: list = field(default_factory=list)
    best: list = field(default_factory=list)
    nodes: Nodes = field(default_factory=Nodes)
    show_cloud: bool = True
    show_best: bool = True

    def set_frame(self, meshes: list[MeshData]) -> None:
        self.nodes.clear()
        self.meshes, self.batches, self.best = meshes, [], []

    def update(self, cloud: ParticleCloud, estimate: np.ndarray | None = None) -> None:
        """The cloud, and the estimate drawn solid: ``estimate`` (K, 4, 4) where given, else the most likely
        particle."""
        if len(cloud.poses) == 0 or not self.meshes:
            return
        scene = self.server.scene
        wxyz, pos = split_pose(cloud.poses)  # (M, K, 4), (M, K, 3)
        best_wxyz, best_pos = (wxyz[0], pos[0]) if estimate is None else split_pose(estimate[None].astype(np.float32))
        best_wxyz, best_pos = best_wxyz.reshape(-1, 4), best_pos.reshape(-1, 3)
        w = np.asarray(cloud.weights, dtype=np.float64)
        rel = w / w.max() if w.max() > 0 else np.ones_like(w)
        tint = colors.apply_map(rel, 0.0, 1.0, colors.WEIGHT)
        # Faint, so the solid most likely scene shows through; the unlikely ones almost gone, so that many of them
        # do not add up to a haze.
        opacity = (0.04 + 0.5 * rel).astype(np.float32)
        if self.batches and len(self.batches[0].batched_positions) != len(w):
            for b in self.batches:  # the instance count changed: viser wants all per-instance arrays resized at once
                self.nodes.remove(b)
            self.batches = []
        with self.server.atomic():
            for k, mesh in enumerate(self.meshes):
                if len(self.batches) <= k:
                    vertices, faces = outline_mesh(mesh, cloud=True)
                    handle = self.nodes.add(scene.add_batched_meshes_simple(
                        f"/particles/{k}", vertices, faces, batched_wxyzs=wxyz[:, k],
                        batched_positions=pos[:, k], batched_colors=tint, batched_opacities=opacity,
                        lod="off", wireframe=True, visible=self.show_cloud, **NO_SHADOW,
                    ))
                    handle.on_click(self._clicked)
                    self.batches.append(handle)
                else:
                    b = self.batches[k]
                    b.batched_positions, b.batched_wxyzs = pos[:, k], wxyz[:, k]
                    b.batched_colors, b.batched_opacities = tint, opacity
                if len(self.best) <= k:
                    self.best.append(self.nodes.add(scene.add_mesh_simple(
                        f"/best/{k}", *mesh.solid_mesh(), color=colors.object_color(k), wxyz=best_wxyz[k],
                        position=best_pos[k], visible=self.show_best, **NO_SHADOW)))
                else:
                    self.best[k].wxyz, self.best[k].position = best_wxyz[k], best_pos[k]

    def _clicked(self, event: viser.SceneNodePointerEvent) -> None:
        if event.instance_index is not None:
            self.on_pick(int(event.instance_index))

    def set_visible(self, cloud: bool, best: bool) -> None:
        self.show_cloud, self.show_best = cloud, best
        for h in self.batches:
            h.visible = cloud
        for h in self.best:
            h.visible = best


@dataclass
class ChosenLayer:
    """One particle's scene before (red) and after (object colours) physics: one of them, both overlaid with a line
    per object showing how physics moved it, or side by side: before left of the observation, after right of it."""

    server: viser.ViserServer
    meshes: list[MeshData] = field(default_factory=list)
    shifts: dict = field(default_factory=dict)
    nodes: Nodes = field(default_factory=Nodes)
    before: list = field(default_factory=list)
    after: list = field(default_factory=list)
    extras: Nodes = field(default_factory=Nodes)
    last: Chosen | None = None

    def set_frame(self, view: ObservationView) -> None:
        self.nodes.clear()
        self.extras.clear()
        self.meshes, self.last = view.meshes, None
        # Side by side: "before" to the left of the objects and "after" to the right, as the sensor sees them, so
        # the observation stays in the middle. The sensor's x axis, flattened onto the table, is "right".
        right = view.T_world_cam[:3, 0] * np.array([1.0, 1.0, 0.0])
        right /= max(np.linalg.norm(right), 1e-9)
        x0, x1, y0, y1 = view.region
        reach = float(np.hypot(x1 - x0, y1 - y0)) + 0.05
        self.shifts = {"before": -reach * right, "after": reach * right}
        scene = self.server.scene
        # "Before" as an outline (as ground truth and labels): the resting scene shows through it, and a YCB scan's
        # every triangle edge was a red haze.
        self.before = [
            self.nodes.add(scene.add_line_segments(f"/chosen/before/{k}", outline_segments(m),
                                                   colors=colors.BEFORE_COLOR, thickness=OUTLINE_WIDTH,
                                                   thickness_units="screen", visible=False))
            for k, m in enumerate(view.meshes)
        ]
        # "After" wears the objects' own colours, like the most likely scene: when the chosen particle is the most
        # likely one the two coincide, and equal colours hide the z-fighting.
        self.after = [
            self.nodes.add(scene.add_mesh_simple(f"/chosen/after/{k}", *m.solid_mesh(),
                                                 color=colors.object_color(k), visible=False, **NO_SHADOW))
            for k, m in enumerate(view.meshes)
        ]

    def update(self, chosen: Chosen | None, mode: str) -> None:
        """Show ``chosen`` (None: the one shown last, if any) in ``mode``."""
        self.last = chosen if chosen is not None else self.last
        c = self.last
        self.extras.clear()
        show = {
            "before": c is not None and mode in ("before physics", "before + after", "side by side"),
            "after": c is not None and mode in ("after physics", "before + after", "side by side"),
        }
        side = mode == "side by side"
        with self.server.atomic():
            for which, handles in (("before", self.before), ("after", self.after)):
                shift = self.shifts[which] if side else np.zeros(3)
                for k, h in enumerate(handles):
                    h.visible = show[which]
                    if not show[which]:
                        continue
                    q, t = split_pose(getattr(c, which)[k])
                    h.wxyz, h.position = q, t + shift
                if side and show[which]:
                    poses = getattr(c, which)
                    above = [0.0, 0.0, poses[:, 2, 3].max() + 0.08]
                    top = poses[:, :3, 3].mean(axis=0) * np.array([1.0, 1.0, 0.0]) + above
                    self.extras.add(self.server.scene.add_label(
                        f"/chosen/{which}_label", f"{which} physics", position=top + shift
                    ))
            if c is not None and mode == "before + after":
                segments = np.stack([c.before[:, :3, 3], c.after[:, :3, 3]], axis=1).astype(np.float32)
                self.extras.add(self.server.scene.add_line_segments(
                    "/chosen/moves", segments, colors=colors.MOVE_COLOR, thickness=3.0, thickness_units="screen"
                ))


    def clear(self) -> None:
        """Nothing chosen (a reset run): hide both scenes and the lines."""
        self.last = None
        self.update(None, "hidden")


@dataclass
class HeatmapLayer:
    """A scene's per-pixel log-likelihood or residual on the observed points of the problem grid: the chosen
    particle's, or (a second layer at another ``path``) the labelled scene's."""

    server: viser.ViserServer
    path: str = "/heatmap"
    view: ObservationView | None = None
    nodes: Nodes = field(default_factory=Nodes)

    def set_frame(self, view: ObservationView) -> None:
        self.nodes.clear()
        self.view = view

    def update(self, chosen: Chosen | None, mode: str) -> tuple[str, np.ndarray | None]:
        """Redraw for the chosen particle -> (legend HTML, the heatmap as an (h, w, 3) image for the panel, or None)."""
        if chosen is None:
            self.nodes.clear()
            return "", None
        return self.draw(chosen.pixel_loglik, chosen.residual, chosen.loglik, mode, f"particle rank {chosen.rank}")

    def draw(self, pixel_loglik: np.ndarray, residual: np.ndarray, loglik: float, mode: str,
             subject: str) -> tuple[str, np.ndarray | None]:
        """Redraw one scene's maps (``mode``: one of HEATMAP_MODES) -> (legend HTML, (h, w, 3) image or None)."""
        self.nodes.clear()
        if self.view is None or mode == "off" or pixel_loglik.shape != self.view.grid_mask.shape:
            return "", None
        mask = self.view.grid_mask
        if mode == "residual":
            values = residual.astype(np.float64) * 100.0  # cm
            finite = np.abs(values[mask])
            finite = finite[np.isfinite(finite)]
            limit = max(0.5, float(np.percentile(finite, 98))) if finite.size else 1.0
            lo, hi, stops, unit = -limit, limit, colors.DIVERGING, "cm"
            note = "observed minus predicted depth: blue where the observation is nearer; grey: nothing predicted"
        else:
            values = pixel_loglik.astype(np.float64)
            lo, hi = colors.robust_range(values[mask])
            stops, unit = colors.MISFIT, "per pixel"
            note = f"total {loglik:.1f}; dark = poorly explained, pale = well explained"
        rgb = colors.apply_map(values, lo, hi, stops)  # (h, w, 3)
        self.nodes.add(self.server.scene.add_point_cloud(
            self.path, self.view.grid_points, rgb[mask], point_size=self.view.grid_point_size,
            point_shape="square", precision="float32",
        ))
        legend = colors.legend_html(f"{mode} ({unit}), {subject}", f"{lo:.2f}", f"{hi:.2f}", stops, note)
        image = np.where(mask[..., None], rgb, 0).astype(np.uint8)
        return legend, image
