"""What the estimator is given: a camera, an observed depth frame and the object models.

Frames (README, "Conventions"): the *table frame* ("world") has z up and the support surface at z = 0; the
camera frame is OpenCV's (x right, y down, z forward). ``T_cam_world`` maps table-frame points into the camera.
Depth images are float32 metres along the camera z axis, 0 where the sensor gave no reading.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh


@dataclass(frozen=True)
class Camera:
    """A pinhole camera. ``K``: (3, 3) intrinsics in pixels; image ``width`` x ``height``;
    ``T_cam_world``: (4, 4) table frame -> camera frame, or None while the table is not yet known."""

    K: np.ndarray
    width: int
    height: int
    T_cam_world: np.ndarray | None = None

    def with_pose(self, T_cam_world: np.ndarray) -> "Camera":
        return Camera(self.K, self.width, self.height, np.asarray(T_cam_world, dtype=np.float64))

    def scaled(self, s: float) -> "Camera":
        """The same camera at ``s`` times the resolution (pixel centres stay consistent)."""
        K = self.K.copy().astype(np.float64)
        K[0, 0] *= s
        K[1, 1] *= s
        # Pixel centres sit at (u + 0.5); scaling keeps the continuous image plane fixed.
        K[0, 2] = (K[0, 2] + 0.5) * s - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * s - 0.5
        return Camera(K, int(round(self.width * s)), int(round(self.height * s)), self.T_cam_world)

    def cropped(self, x0: int, y0: int, width: int, height: int) -> "Camera":
        """The camera of the sub-image ``[y0:y0+height, x0:x0+width]``."""
        K = self.K.copy().astype(np.float64)
        K[0, 2] -= x0
        K[1, 2] -= y0
        return Camera(K, width, height, self.T_cam_world)


@dataclass
class ObjectModel:
    """One known object. ``mesh`` is in metres in the object's own frame (BOP model frame).

    ``symmetries``: (S, 4, 4) object-frame transforms under which the object looks the same (identity first).
    ``name``: what the user sees (models_info.json's ``name``, else ``obj_000006``).
    """

    obj_id: int
    mesh: trimesh.Trimesh
    name: str = ""
    density: float = 1000.0  # kg/m^3; the paper's "density 1.0" in g/cm^3
    friction: float = 0.75
    symmetries: np.ndarray = field(default_factory=lambda: np.eye(4)[None])
    source: Path | None = None

    def __post_init__(self) -> None:
        if not self.name:
            self.name = f"obj_{self.obj_id:06d}"

    @property
    def mass(self) -> float:
        """kg. Volume of the mesh (or its convex hull when it is not watertight) times density."""
        volume = self.mesh.volume if self.mesh.is_watertight else self.mesh.convex_hull.volume
        return float(abs(volume) * self.density)


@dataclass
class Frame:
    """One observed depth frame and what is known about it.

    ``depth``: (H, W) float32 metres, 0 = no reading. ``object_ids``: the objects present (what a recognition
    system would report; order defines the estimator's state). ``gt_T_cam_obj``: (K, 4, 4) ground truth in the
    camera frame, only for scoring and display, never given to the estimator.
    """

    depth: np.ndarray
    camera: Camera
    object_ids: list[int]
    scene_id: int = 0
    im_id: int = 0
    gt_T_cam_obj: np.ndarray | None = None
    rgb: np.ndarray | None = None
    source: Path | None = None


@dataclass(frozen=True)
class Table:
    """The support surface in the table frame: the top at z = 0, a rectangle ``[x_min, x_max] x [y_min, y_max]``
    (metres). ``region_*``: where the objects are seen (the bounding box of the points above the table), which is
    where the estimator draws its initial particles."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float
    region_min: tuple[float, float] = (-0.15, -0.15)
    region_max: tuple[float, float] = (0.15, 0.15)


def display_names(models) -> list[str]:
    """One name per object of the scene, as the workbench and the command line show it: the model's name, with
    " #2", " #3", ... on further instances of the same model."""
    seen: dict[str, int] = {}
    out = []
    for m in models:
        base = m.name or f"obj_{m.obj_id:06d}"
        seen[base] = seen.get(base, 0) + 1
        out.append(base if seen[base] == 1 else f"{base} #{seen[base]}")
    return out
