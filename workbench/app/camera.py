"""Camera presets of the 3D view: framing the objects, and looking from the depth sensor.

Poses are in the table frame (viser's world; z up). A preset is applied to a browser tab's camera
(``viser.CameraHandle``) or to the server's initial camera (where new tabs and reloads start). Only position and
target: setting the up vector or the field of view as well made a newly opened tab hang in software WebGL.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.app.protocol import ObservationView

FRAME_OBJECTS = "Frame objects"
FROM_SENSOR = "From the sensor"
VIEWER_FOV = np.radians(75.0)  # viser's vertical field of view (three.js's default)
FILL = 0.35  # share of the view's height the object region's diagonal takes when framed
PANEL_SHIFT = 0.19  # the panel covers the right quarter of the page: aim right of the objects by this x distance


@dataclass(frozen=True)
class CameraPose:
    position: tuple[float, float, float]
    look_at: tuple[float, float, float]


def frame_objects(view: ObservationView) -> CameraPose:
    """From the sensor's side and elevation, close enough that the object region fills most of the view (and the
    sensor's frustum stays behind the viewer), with the objects left of centre, clear of the panel."""
    rx0, rx1, ry0, ry1 = view.region
    target = np.array([(rx0 + rx1) / 2, (ry0 + ry1) / 2, 0.02])
    toward_sensor = view.T_world_cam[:3, 3] - target
    toward_sensor /= np.linalg.norm(toward_sensor)
    diagonal = max(0.1, float(np.hypot(rx1 - rx0, ry1 - ry0)))
    distance = 0.5 * diagonal / np.tan(VIEWER_FOV / 2) / FILL
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
