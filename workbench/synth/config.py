"""What the generator makes: the scene categories, the desks of the real-like ones, and ``SynthConfig``, how
scenes are drawn, simulated, viewed and sensed."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from workbench.synth.sensor.model import SensorModel

PAPER_CATEGORIES = ("touching", "stacked", "slant", "occluded", "three", "four")
SHAPE_CATEGORIES = ("ycb_clutter", "raised", "leaning", "tools")  # real shapes: drawn from given models only
CATEGORIES = PAPER_CATEGORIES + ("clutter", "mixed", "handle_hidden", "handle_shown", "lying") + SHAPE_CATEGORIES
# new ones go last: a category's index seeds its scenes
MODEL_CATEGORIES = ("lying",) + SHAPE_CATEGORIES  # those that can draw from any models (``make-scenes --models``)
HANDLE_CATEGORIES = ("handle_hidden", "handle_shown")  # the mug, its handle hidden behind its body or in view


@dataclass(frozen=True)
class SynthConfig:
    """How scenes are drawn, simulated, viewed and sensed. Lengths metres, angles degrees."""

    width: int = 640
    height: int = 480
    focal_640: float = 525.0  # Kinect v1 focal length at 640 pixels wide; scaled with the width
    table_size: tuple[float, float] = (1.2, 0.8)
    table_thickness: float = 0.04
    floor_z: float = -0.75
    cam_distance: tuple[float, float] = (0.7, 1.0)
    cam_elevation: tuple[float, float] = (45.0, 70.0)
    hide_azimuth_jitter: float = 15.0  # camera azimuth spread around "the tall box is in front of the small one"
    dt: float = 1.0 / 1000.0
    settle_max_s: float = 3.0
    rest_speed: float = 2e-3  # m/s (and rad/s times 0.1 m) below which a body counts as at rest
    rest_steps: int = 100  # ... for this many consecutive steps
    density: float = 400.0  # kg/m^3, filled cardboard boxes
    friction: float = 0.75
    lift: float = 3e-4  # boxes start this far above the table and drop onto it
    contact_tol: float = 1e-3  # a contact point this close counts as touching
    flat_tol: float = 3.0  # a box resting on a face tilts less than this
    slant_range: tuple[float, float] = (10.0, 80.0)
    hidden_max_visib: float = 0.1
    handle_hidden_elevation: tuple[float, float] = (15.0, 35.0)  # low enough that the body hides the handle
    handle_hidden_jitter: float = 25.0  # camera azimuth spread around "the handle points straight away"
    handle_max_hidden_px: int = 3  # handle pixels a "hidden" view may show (a stray edge pixel)
    handle_min_shown_px: int = 60  # handle pixels a "shown" view must show (at 640 pixels wide)
    shown_min_visib: float = 0.15
    max_layout_tries: int = 300
    max_camera_tries: int = 40
    distractor_clearance: float = 0.03  # seen from above, between a distractor and any object of interest
    clutter_count: tuple[int, int] = (6, 8)  # ``ycb_clutter``'s objects (inclusive; fewer when fewer are given)
    free_clearance: float = 0.015  # between an object placed free and the others (real shapes: a crowded desk)
    raised_extents: tuple[tuple[float, float], ...] = ((0.30, 0.50), (0.30, 0.50), (0.05, 0.20))  # ``raised``'s box
    sensor: SensorModel = field(default_factory=SensorModel)
    objects: tuple = ()  # the objects (``objects.Item``) ``MODEL_CATEGORIES`` draw from; empty: the built-in ones

    def K(self) -> np.ndarray:
        """Kinect-like intrinsics; principal point at the image centre (pixel centres at integer u, v)."""
        f = self.focal_640 * self.width / 640.0
        return np.array([[f, 0.0, (self.width - 1) / 2.0], [0.0, f, (self.height - 1) / 2.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class DeskSpec:
    """What a category adds to the paper's bare table to look like a real desk. Lengths metres."""

    distractors: tuple[int, int] = (0, 0)  # how many objects the estimator is not told about (inclusive range)
    table_pose: float = 1.0  # probability that scene_camera.json gives the table pose (cam_R_w2c, cam_t_w2c)
    table_size: tuple[tuple[float, float], tuple[float, float]] | None = None  # x, y ranges; None: SynthConfig's


# Desks up to 2.4 x 1.5 m: larger than the camera's view of them (about 1.2 x 0.9 m at 1 m).
LARGE_DESK = ((0.9, 2.4), (0.7, 1.5))
DESKS = {"clutter": DeskSpec((2, 4), 0.5, LARGE_DESK), "mixed": DeskSpec((1, 3), 0.0, LARGE_DESK),
         "ycb_clutter": DeskSpec((2, 4), 0.5, LARGE_DESK), "raised": DeskSpec((0, 2), 0.0, LARGE_DESK),
         "leaning": DeskSpec((0, 2), 0.5, LARGE_DESK), "tools": DeskSpec((1, 3), 0.5, LARGE_DESK)}
