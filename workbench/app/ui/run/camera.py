"""Camera presets of the 3D view: framing the objects, and looking from the depth sensor.

Poses are in the table frame (viser's world; z up). A preset is applied to a browser tab's camera
(``viser.CameraHandle``) or to the server's initial camera (where new tabs and reloads start). Only position and
target: setting the up vector or the field of view as well made a newly opened tab hang in software WebGL.
``TabCameras`` applies them, and remembers where the user left a tab's camera for the tabs opened later.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import viser

from workbench.app.protocol import ObservationView
from workbench.app.ui.ui_thread import Later, UiThread

FRAME_OBJECTS = "Frame objects"
FROM_SENSOR = "From the sensor"
VIEWER_FOV = np.radians(75.0)  # viser's vertical field of view (three.js's default)
FILL = 0.35  # share of the view's height the object region's diagonal takes when framed
FILL_OBJECTS = 0.6  # or the diagonal of the objects' bounding box, where it is known: closer
CAMERA_REST_S = 0.5  # a tab's camera is remembered (for reloads and new tabs) once it rested this long
PANEL_SHIFT = 0.19  # the panel covers the right quarter of the page: aim right of the objects by this x distance


@dataclass(frozen=True)
class CameraPose:
    position: tuple[float, float, float]
    look_at: tuple[float, float, float]


def objects_box(view: ObservationView, poses: np.ndarray | None) -> tuple[np.ndarray, float] | None:
    """The bounding box of the objects posed by ``poses`` (K, 4, 4; table frame), else by the frame's ground
    truth -> (its centre (3,), its diagonal m); None where neither places any object."""
    if poses is None or len(poses) != len(view.meshes):
        poses = view.gt_T_world_obj
    if poses is None:
        return None
    points = [np.asarray(m.vertices) @ T[:3, :3].T + T[:3, 3] for m, T in zip(view.meshes, poses)
              if np.all(np.isfinite(T))]
    if not points:
        return None
    lo, hi = np.min([p.min(axis=0) for p in points], axis=0), np.max([p.max(axis=0) for p in points], axis=0)
    return (lo + hi) / 2, float(np.linalg.norm(hi - lo))


def frame_objects(view: ObservationView, poses: np.ndarray | None = None) -> CameraPose:
    """From the sensor's side and elevation, close enough that the objects (posed by ``poses``, the estimate;
    else by the ground truth; else the object region) fill most of the view (and the sensor's frustum stays behind
    the viewer), with the objects left of centre, clear of the panel."""
    box = objects_box(view, poses)
    if box is not None:
        target, diagonal, fill = box[0], max(0.05, box[1]), FILL_OBJECTS
    else:  # nothing placed yet: the region where the objects are searched for
        rx0, rx1, ry0, ry1 = view.region
        target = np.array([(rx0 + rx1) / 2, (ry0 + ry1) / 2, 0.02])
        diagonal, fill = max(0.1, float(np.hypot(rx1 - rx0, ry1 - ry0))), FILL
    toward_sensor = view.T_world_cam[:3, 3] - target
    toward_sensor /= np.linalg.norm(toward_sensor)
    distance = 0.5 * diagonal / np.tan(VIEWER_FOV / 2) / fill
    right = view.T_world_cam[:3, 0] * np.array([1.0, 1.0, 0.0])
    aim = target + PANEL_SHIFT * distance * right / max(np.linalg.norm(right), 1e-9)
    eye = aim + toward_sensor * distance
    return CameraPose(tuple(map(float, eye)), tuple(map(float, aim)))


def from_sensor(view: ObservationView) -> CameraPose:
    """Where the depth sensor was, looking along its optical axis: the 3D view then shows the scene as the depth
    image does (with the viewer's wider field of view)."""
    T = view.T_world_cam
    eye = T[:3, 3]
    aim = eye + T[:3, 2] * 0.5  # any point on the optical axis
    return CameraPose(tuple(map(float, eye)), tuple(map(float, aim)))


def apply_camera(camera, pose: CameraPose) -> None:
    """Set a ``viser.CameraHandle`` or the server's ``initial_camera`` to ``pose``."""
    camera.position = pose.position
    camera.look_at = pose.look_at


class TabCameras:
    """Where browser tabs look: a preset applied to one tab or to all, and the camera a tab last rested at,
    remembered as the server's initial camera, so that a new tab or a reload starts there and not back at the
    default view."""

    def __init__(self, server: viser.ViserServer, ui: UiThread):
        self.server, self.ui = server, ui
        self.pose: CameraPose | None = None  # where new and reloaded tabs start
        self._moved: CameraPose | None = None
        self._timer: Later | None = None

    def preset(self, view: ObservationView | None, which: str, client: viser.ClientHandle | None,
               poses: np.ndarray | None = None) -> None:
        """Point the camera at the objects (``FRAME_OBJECTS``; ``poses``: where they are now, see
        ``frame_objects``) or put it where the depth sensor was; for one browser tab (``client``) or every tab and
        every later one."""
        if view is None:
            return
        pose = frame_objects(view, poses) if which == FRAME_OBJECTS else from_sensor(view)
        self.set_initial(pose)
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            apply_camera(c.camera, pose)

    def set_initial(self, pose: CameraPose) -> None:
        """Where a new or reloaded tab starts."""
        self.pose = pose
        apply_camera(self.server.initial_camera, pose)

    def client_connected(self, client: viser.ClientHandle) -> None:
        """A new tab (or a reload) starts where the last camera was left, not back at the default view."""
        def moved(camera: viser.CameraHandle) -> None:
            self._moved = CameraPose(tuple(camera.position), tuple(camera.look_at))
            due = self._timer is None
            if due:  # remembered once the camera has rested a moment: a drag reports ~30 poses a second
                self._timer = self.ui.later(CAMERA_REST_S, self._remember)

        client.camera.on_update(self.ui.callback(moved))

    def _remember(self) -> None:
        pose, self._timer = self._moved, None
        if pose is not None:
            self.set_initial(pose)
