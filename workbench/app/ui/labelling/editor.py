"""Editing labels in the browser: per object a pose with a transform gizmo and a magenta mesh in the 3D view, and
the selected object's pose fields in the Label tab.

A label is an object's pose T_world_obj in the table frame. The selected object has a transform gizmo, and six
numeric fields (x, y, z in cm; roll, pitch, yaw in degrees, ``R = Rz(yaw) Ry(pitch) Rx(roll)`` about the table's
axes) that follow it; typing into a field moves the gizmo. Labelled objects are drawn in magenta (beside their gizmo
rather than as its child: three.js hides the children of a hidden node, and only the selected object's gizmo is
shown). An unlabelled object's gizmo and fields show the most likely scene; moving or typing labels it. Every edit
is sent to the engine as ``SetLabels``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import viser

from workbench.app import protocol as p
from workbench.app.ui.labelling.controls import AXES, FACES, NO_OBJECT, TURNS, LabelTab
from workbench.app.ui.labelling.pose_fields import PoseFields
from workbench.app.ui.run.views import OUTLINE_WIDTH, Nodes, outline_segments, split_pose
from workbench.app.ui.ui_thread import UiThread
from workbench.app.ui.widgets.colors import LABEL_COLOR
from workbench.app.ui.widgets.quiet import Quiet
from workbench.geometry import (
    euler_to_matrix,
    make_pose,
    quat_wxyz_to_matrix,
    rot_x,
    rotvec_to_matrix,
)

SEND_INTERVAL_S = 0.05  # gizmo drags report ~60 poses/s; the engine only ever renders the latest anyway
GIMBAL_DEG = 80.0  # |pitch| beyond this: roll and yaw nearly turn about one axis and typing them stops helping


def turned(T: np.ndarray, R: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Pose ``T`` (4, 4) rotated by ``R`` (3, 3, about the table's axes) about the object's origin, then raised or
    lowered so that its lowest point (of ``vertices`` (V, 3), object frame) stays at the same height: an object
    resting on the table stays on it."""
    low = float(np.min(vertices @ T[:3, :3].T[:, 2]))
    out = make_pose(R @ T[:3, :3], T[:3, 3])
    out[2, 3] += low - float(np.min(vertices @ out[:3, :3].T[:, 2]))
    return out


def laid_on(T: np.ndarray, face: tuple[float, float, float], vertices: np.ndarray) -> np.ndarray:
    """Pose ``T`` turned so that the object's own axis ``face`` points down, keeping its place on the table and as
    much of its heading as the turn allows, resting on the table (lowest point at z = 0)."""
    d = T[:3, :3] @ np.asarray(face, dtype=np.float64)  # that axis now, in the table frame
    down = np.array([0.0, 0.0, -1.0])
    axis = np.cross(d, down)
    s, c = np.linalg.norm(axis), float(np.dot(d, down))
    if s < 1e-9:  # already down, or straight up: a half turn about the table's x
        R = np.eye(3) if c > 0 else rot_x(np.pi)
    else:  # the shortest rotation taking d onto down: about their cross product, by the angle between them
        R = rotvec_to_matrix(axis / s * np.arctan2(s, c))
    out = make_pose(R @ T[:3, :3], T[:3, 3])
    out[2, 3] = -float(np.min(vertices @ out[:3, :3].T[:, 2]))  # lowest point on the table top
    return out


@dataclass
class LabelEditor:
    """The labels as the panel shows them (per object a (4, 4) table-frame pose or None), their gizmos and meshes,
    and the fields of the selected object. ``send`` reaches the engine; ``on_unlabelled`` is told when the last
    label was cleared (the label heatmap has nothing left to show)."""

    server: viser.ViserServer
    tab: LabelTab
    send: Callable[[object], None]
    ui: UiThread
    quiet: Quiet
    reporter: object  # shows a refused typed value (``Reporter.field_errors``)
    on_unlabelled: Callable[[], None] = lambda: None
    fields: PoseFields = field(init=False)
    labels: list = field(default_factory=list)
    estimate: np.ndarray | None = None  # the most likely scene (K, 4, 4): where unlabelled objects are shown
    names: list[str] = field(default_factory=list)
    vertices: list = field(default_factory=list)  # per object (V, 3), object frame
    homes: np.ndarray | None = None  # (K, 4, 4): where an object sits before there is any estimate
    gizmos: list = field(default_factory=list)
    meshes: list = field(default_factory=list)
    nodes: Nodes = field(default_factory=Nodes)
    shown: bool = True  # the labels' outlines shown (the View box's visibility bar)
    _last_send: float = 0.0

    def __post_init__(self) -> None:
        t, on_ui = self.tab, self.ui.callback
        t.object.on_update(on_ui(lambda _: self.guarded(self.selection_changed)))
        self.fields = PoseFields(t, self.ui, self.quiet, self.reporter, self.field_edited)
        t.show_gizmo.on_update(on_ui(lambda _: self.guarded(self.redraw)))
        for axis, h in zip(AXES, t.turns):
            h.on_click(on_ui(lambda event, axis=axis: self.guarded(lambda: self.turn(axis, event.target.value))))
        t.lay.on_click(on_ui(lambda event: self.guarded(lambda: self.lay_on(event.target.value))))
        t.clear.on_click(on_ui(lambda _: self.guarded(self.clear_selected)))

    def guarded(self, action: Callable[[], None]) -> None:
        """Run a GUI callback unless the server itself is writing the controls (see ``Quiet``)."""
        if not self.quiet.active:
            action()

    def set_frame(self, view: p.ObservationView) -> None:
        """New frame: one gizmo and one mesh per object, nothing labelled until the engine says."""
        self.nodes.clear()
        scene = self.server.scene
        K = len(view.meshes)
        self.labels, self.estimate = [None] * K, None
        self.names = [m.name for m in view.meshes]  # unique per scene (scene.display_names)
        self.vertices = [np.asarray(m.vertices, dtype=np.float64) for m in view.meshes]
        x0, x1, y0, y1 = view.region
        self.homes = np.stack([
            make_pose(np.eye(3), [(x0 + x1) / 2, (y0 + y1) / 2, -float(np.min(m.vertices[:, 2]))])
            for m in view.meshes
        ])
        self.gizmos, self.meshes = [], []
        for k, m in enumerate(view.meshes):
            size = float(np.max(np.ptp(m.vertices, axis=0)))
            gizmo = self.nodes.add(scene.add_transform_controls(
                f"/label/{k}", scale=max(0.06, 1.2 * size), line_width=2.0, depth_test=False, visible=False,
            ))
            gizmo.on_update(self.ui.callback(lambda event, k=k: self.gizmo_moved(k, event)))
            self.gizmos.append(gizmo)
            # An outline, as the ground truth's: the depth's points and the estimate stay visible inside it.
            self.meshes.append(self.nodes.add(scene.add_line_segments(
                f"/label_mesh/{k}", outline_segments(m), colors=LABEL_COLOR, thickness=OUTLINE_WIDTH + 0.5,
                thickness_units="screen", visible=False)))
        with self.quiet:
            self.tab.object.options = tuple(self.names) or (NO_OBJECT,)
            self.tab.object.value = self.tab.object.options[0]
        self.redraw()

    def set_labels(self, labels) -> None:
        """The labels the engine holds."""
        self.labels = [None if T is None else np.array(T, dtype=np.float64) for T in labels]
        self.redraw(confirmed=True)

    def show_estimate(self, best: np.ndarray | None) -> None:
        """The latest most likely scene: an unlabelled selected object (gizmo and fields) follows it. Only that one:
        this runs every iteration, and hidden gizmos are placed when they are selected."""
        self.estimate = None if best is None else np.asarray(best, dtype=np.float64)
        sel = self.selected()
        if sel is None or self.labels[sel] is not None:
            return
        with self.server.atomic(), self.quiet:
            gizmo = self.gizmos[sel]
            gizmo.wxyz, gizmo.position = split_pose(self.pose(sel))
            self.show_fields(sel)

    def selected(self) -> int | None:
        try:
            return self.names.index(self.tab.object.value)
        except ValueError:
            return None

    def pose(self, k: int) -> np.ndarray:
        """Where object k is shown: its label, else the best estimate, else its place before any estimate."""
        if self.labels[k] is not None:
            return self.labels[k]
        if self.estimate is not None and len(self.estimate) == len(self.labels):
            return self.estimate[k]
        return self.homes[k]

    def redraw(self, confirmed: bool = False) -> None:
        """Gizmo, meshes and fields from the labels (the server writing: no callback may echo this back);
        ``confirmed``: the labels are the engine's answer (``PoseFields.show``)."""
        sel = self.selected()
        with self.server.atomic(), self.quiet:
            for k, (gizmo, mesh) in enumerate(zip(self.gizmos, self.meshes)):
                q, t = split_pose(self.pose(k))
                gizmo.wxyz, gizmo.position = q, t
                gizmo.visible = k == sel and self.tab.show_gizmo.value
                mesh.wxyz, mesh.position = q, t
                mesh.visible = self.labels[k] is not None and self.shown
            self.show_fields(sel, confirmed)

    def set_shown(self, shown: bool) -> None:
        """Show or hide the labels' outlines (the View box's visibility bar)."""
        self.shown = shown
        with self.server.atomic():
            for k, mesh in enumerate(self.meshes):
                mesh.visible = self.labels[k] is not None and shown

    def show_fields(self, sel: int | None, confirmed: bool = False) -> None:
        t = self.tab
        if sel is None:
            t.state.content = "Load a frame to label its objects."
            return
        self.fields.show(self.pose(sel), confirmed)
        pitch = self.fields.values[4]
        if abs(pitch) > GIMBAL_DEG:
            gimbal = (f" Pitch is {pitch:.0f}°: roll and yaw now turn about nearly the same axis, so use **Turn**, "
                      "**Lay on face** or the gizmo rather than typing angles.")
        else:
            gimbal = ""
        if self.labels[sel] is not None:
            state = f"**{self.names[sel]}** is labelled.{gimbal}"
        else:
            shown = "the best estimate" if self.estimate is not None else "a starting place"
            state = (f"**{self.names[sel]}** is not labelled: the fields show {shown}. Type a value or drag the gizmo "
                     f"to label it.{gimbal}")
        if t.state.content != state:  # markdown is re-sent on every assignment, changed or not
            t.state.content = state


    # -- edits

    def selection_changed(self) -> None:
        self.start_editing()
        self.redraw()

    def start_editing(self) -> None:
        """The user is labelling: show the selected object's gizmo (off until now, see ``build_label_tab``)."""
        if not self.tab.show_gizmo.value:
            with self.quiet:
                self.tab.show_gizmo.value = True

    def turn(self, axis: str, which: str) -> None:
        """A ``Turn about`` button: a quarter turn of the selected object about the table's ``axis``."""
        k = self.selected()
        if k is None:
            return
        angle = np.pi / 2 if which == TURNS[1] else -np.pi / 2
        self.set_label(k, turned(self.pose(k), AXES[axis](angle), self.vertices[k]))

    def lay_on(self, face: str) -> None:
        """A ``Lay on face`` button: the selected object turned onto that face of its own, on the table."""
        k = self.selected()
        if k is None:
            return
        self.set_label(k, laid_on(self.pose(k), FACES[face], self.vertices[k]))

    def set_label(self, k: int, T: np.ndarray) -> None:
        self.start_editing()
        self.labels[k] = np.asarray(T, dtype=np.float64)
        self.redraw()
        self.send_labels()

    def field_edited(self, i: int, value: float) -> None:
        """Pose field ``i`` typed (``PoseFields``' order; its rule read ``value``): a position field changes that
        coordinate only; an angle field sets the rotation from the three angles shown, that one changed (so the
        other coordinates are kept to the last bit)."""
        k = self.selected()
        if k is None:
            return
        T = np.array(self.pose(k), dtype=np.float64)
        if i < 3:
            T[i, 3] = value / 100.0
        else:
            T[:3, :3] = euler_to_matrix(np.radians(self.fields.angles_with(i, value)))
        self.set_label(k, T)

    def gizmo_moved(self, k: int, event: viser.TransformControlsEvent) -> None:
        if k >= len(self.labels) or self.gizmos[k] is not event.target:
            return  # a late event for the previous frame's gizmo
        R = quat_wxyz_to_matrix(np.asarray(event.target.wxyz, dtype=np.float64))
        self.labels[k] = make_pose(R, np.asarray(event.target.position, dtype=np.float64))
        with self.server.atomic(), self.quiet:
            mesh = self.meshes[k]
            mesh.wxyz, mesh.position, mesh.visible = event.target.wxyz, event.target.position, True
            if self.selected() != k:
                self.tab.object.value = self.names[k]
            self.show_fields(k)
        now = time.monotonic()
        if event.phase != "update" or now - self._last_send >= SEND_INTERVAL_S:
            self.send_labels()

    def clear_selected(self) -> None:
        k = self.selected()
        if k is None:
            return
        self.labels[k] = None
        if not any(T is not None for T in self.labels):
            self.on_unlabelled()
        self.redraw()
        self.send_labels()

    def send_labels(self) -> None:
        self._last_send = time.monotonic()
        self.send(p.SetLabels(tuple(self.labels), heatmap=self.tab.heatmap.value != "off"))
