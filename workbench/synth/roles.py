"""What a given model can be in a scene of real shapes, from its geometry alone (any BOP models, named or not):

- a **box** fills its oriented bounding box (>= 85 %: YCB's cracker, sugar, pudding and gelatin boxes, the wood
  block and the foam brick): it can lean on another object;
- a **vessel** is open at the top in one of its resting poses: a ray straight down its middle meets its own bottom
  more than half its height down, walled in all round there (YCB's bowl and mug; the pitcher's scan is closed at
  the top). A box can lean on it, upright or upturned;
- a **tool** is concave (fills less than 60 % of its convex hull) and no vessel: YCB's drill, clamps and scissors;
- anything else (cans, bottles, the banana, a mesh that is not closed such as YCB's marker) is **other**.
"""

from __future__ import annotations

import functools

import numpy as np
import trimesh

from workbench.geometry import make_pose
from workbench.synth.bodies import piece_rotations
from workbench.synth.objects import MeshItem, model_mesh
from workbench.synth.views import raycast

BOX, VESSEL, TOOL, OTHER = "box", "vessel", "tool", "other"
BOX_FILL = 0.85  # of its bounding box, in the model frame
TOOL_FILL = 0.6  # of its convex hull
OPEN_DEPTH = 0.5  # of its height: how deep rays down a vessel's middle go before they meet it


@functools.cache
def role(item: MeshItem) -> str:
    """The model's role: BOX, VESSEL, TOOL or OTHER (see the module doc)."""
    mesh = model_mesh(item)
    if not mesh.is_watertight:  # no volume to measure
        return OTHER
    volume = abs(float(mesh.volume))
    if volume >= BOX_FILL * float(mesh.bounding_box_oriented.volume):
        return BOX
    if any(_open_at_top(mesh.copy().apply_transform(make_pose(R, np.zeros(3)))) for R in piece_rotations(item)[0]):
        return VESSEL
    return TOOL if volume < TOOL_FILL * abs(float(mesh.convex_hull.volume)) else OTHER


def box_frame(item: MeshItem) -> tuple[np.ndarray, np.ndarray]:
    """A box's faces: its oriented bounding box as (T_obj_box (4, 4), extents (3,) m). YCB's pudding and gelatin
    boxes lie turned in their model frames."""
    box = model_mesh(item).bounding_box_oriented.primitive
    T = np.array(box.transform, dtype=np.float64)
    if np.linalg.det(T[:3, :3]) < 0:
        T[:3, 2] *= -1.0  # the same box in a right-handed frame
    return T, np.asarray(box.extents, dtype=np.float64)


def _open_at_top(mesh: trimesh.Trimesh) -> bool:
    """Is the posed mesh (metres) open at the top: does a ray straight down its middle meet it more than
    ``OPEN_DEPTH`` of its height below its top, and do eight level rays from just above that point all meet it
    (walls all round, not the gap between a drill's handle and its body)?"""
    lo, hi = mesh.bounds
    mid, span = (lo + hi) / 2, hi - lo
    down = np.array([[mid[0], mid[1], hi[2] + 0.01, 0.0, 0.0, -1.0]], dtype=np.float32)
    depth, index = raycast([mesh], down)
    if index[0] != 0 or depth[0] - 0.01 < OPEN_DEPTH * span[2]:
        return False
    a = np.arange(8) * np.pi / 4
    level = np.zeros((8, 6), dtype=np.float32)
    level[:, :3] = [mid[0], mid[1], hi[2] + 0.01 - depth[0] + 0.1 * span[2]]
    level[:, 3], level[:, 4] = np.cos(a), np.sin(a)
    return bool(np.all(raycast([mesh], level)[1] == 0))
