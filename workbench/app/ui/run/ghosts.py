"""The other modes of the posterior in the 3D view: each object's alternatives to the estimate (``modes[1:]``) as
ghosts, faint outlines in a pale tint of the object's colour, each labelled beside it with its object's name and
its probability; a hidden object's hiding places (``posterior.ObjectPosterior.hiding``) as dots of that tint.

Ghosts are drawn as the particles are (``views.outline_mesh``: the feature edges of a coarse decimation, one
instanced wireframe per object), not as solid meshes or every triangle edge: a few more instances cost software
WebGL almost nothing, and the estimate stays readable under them. The nodes are rebuilt only when a new posterior
arrives (a finished run, the best estimate taken as label, a restored session), never per iteration.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import viser

from workbench.app.protocol import MeshData
from workbench.app.ui.run.modes import mode_label
from workbench.app.ui.run.views import NO_SHADOW, Nodes, outline_mesh, split_pose
from workbench.app.ui.widgets import colors
from workbench.inference.answer.posterior import MAX_MODES, Posterior

GHOST_OPACITY = 0.55
LABELLED = MAX_MODES - 1  # an object's other modes that get a label, the most likely first: all but a range's
HIDING_POINT_M = 0.012  # a hiding place's dot: about half the places' spacing, so neighbours stay apart
LABEL_LIFT_M = 0.02  # a label sits this far above the ghost's highest outline point
LABEL_GAP_M = 0.01  # and this far beyond its outline, on the side away from the other objects


def label_position(segments: np.ndarray, T: np.ndarray, away_from: np.ndarray) -> np.ndarray:
    """Where a ghost's label goes: beside its outline ``segments`` (E, 2, 3) object frame, posed by ``T`` (4, 4)
    table frame, on the side away from ``away_from`` (3,) (the estimate's centre: over the middle of the ghost the
    label sat over the other objects), just above its top -> (3,) table frame, m."""
    points = segments.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    if not len(points):
        points = T[None, :3, 3]
    centre = points.mean(axis=0)
    out = centre[:2] - np.asarray(away_from, dtype=np.float64)[:2]
    norm = np.linalg.norm(out)
    out = out / norm if norm > 1e-9 else np.array([1.0, 0.0])
    reach = float(np.max((points[:, :2] - centre[:2]) @ out))  # the outline's extent that way
    xy = centre[:2] + out * (reach + LABEL_GAP_M)
    return np.array([xy[0], xy[1], points[:, 2].max() + LABEL_LIFT_M])


@dataclass
class ModesLayer:
    """Per object with other modes: one instanced outline (an instance per mode after the first) and a label per
    mode ("mug · p = 0.31 turned over its x axis"; the most likely ``LABELLED``); for an object the sensor sees none
    of, a dot at each place it may hide in. ``ghosts[k]``: object k's outline handle, if it has other modes;
    ``hiding[k]``: its dots' handle, if it is hidden; ``labels``: every label's handle; ``texts``: their texts, in
    the order drawn (for the tests)."""

    server: viser.ViserServer
    meshes: list[MeshData] = field(default_factory=list)
    nodes: Nodes = field(default_factory=Nodes)
    ghosts: dict = field(default_factory=dict)
    hiding: dict = field(default_factory=dict)
    labels: list = field(default_factory=list)
    texts: list[str] = field(default_factory=list)
    shown: bool = True

    def set_frame(self, meshes: list[MeshData]) -> None:
        self.clear()
        self.meshes = meshes

    def clear(self) -> None:
        self.nodes.clear()
        self.ghosts, self.hiding, self.labels, self.texts = {}, {}, [], []

    def update(self, posterior: Posterior | None) -> None:
        """Draw ``posterior``'s other modes (None: none), replacing those drawn."""
        self.clear()
        if posterior is None or not self.meshes:
            return
        scene, add = self.server.scene, self.nodes.add
        middle = np.mean([o.modes[0].T[:3, 3] for o in posterior.objects], axis=0)
        with self.server.atomic():
            for o in posterior.objects:
                if o.obj >= len(self.meshes):
                    continue
                if o.hiding is not None:
                    self.hiding[o.obj] = add(scene.add_point_cloud(
                        f"/modes/{o.obj}/hiding", o.hiding.places.astype(np.float32),
                        np.array(colors.ghost_color(o.obj), np.uint8), point_size=HIDING_POINT_M, point_shape="circle",
                        visible=self.shown))
                others = o.modes[1:]
                if not others:
                    continue
                mesh, k = self.meshes[o.obj], o.obj
                poses = np.stack([m.T for m in others])
                wxyz, pos = split_pose(poses)
                vertices, faces = outline_mesh(mesh)
                n = len(others)
                self.ghosts[k] = add(scene.add_batched_meshes_simple(
                    f"/modes/{k}/ghosts", vertices, faces, batched_wxyzs=wxyz, batched_positions=pos,
                    batched_colors=np.tile(np.array(colors.ghost_color(k), np.uint8), (n, 1)),
                    batched_opacities=np.full(n, GHOST_OPACITY, np.float32),
                    lod="off", wireframe=True, visible=self.shown, **NO_SHADOW))
                segments = vertices.reshape(-1, 2, 3)
                # The most likely few are labelled: an open range's headings, 20 degrees apart, are all modes, and
                # a label each would stack a dozen around one mug; the Inspect tab lists them all.
                for j, m in enumerate(others[:LABELLED], start=1):
                    text = f"{mesh.name} · {mode_label(o, m)}"
                    self.labels.append(add(scene.add_label(
                        f"/modes/{k}/label_{j}", text, position=label_position(segments, m.T, middle),
                        anchor="bottom-center", visible=self.shown)))
                    self.texts.append(text)

    def set_visible(self, shown: bool) -> None:
        self.shown = shown
        for h in (*self.ghosts.values(), *self.hiding.values(), *self.labels):
            h.visible = shown
