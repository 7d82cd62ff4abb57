"""One frame from plain files, for users without a BOP dataset.

- Depth: ``.png`` (16-bit, value x ``depth_scale`` = millimetres) or ``.npy`` (float metres; NaN, inf and values
  <= 0 mean no reading).
- Intrinsics JSON::

    {"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]      (or 9 numbers, or "fx", "fy", "cx", "cy"),
     "width": W, "height": H,                        (optional; checked against the depth image)
     "depth_scale": 1.0,                             (PNG only: millimetres per unit, default 1)
     "T_cam_world": 4x4 metres                       (optional: table frame, z up, top at z = 0, -> camera;
                                                      or "cam_R_w2c" 9 numbers + "cam_t_w2c" 3 numbers in mm)}

- Meshes: any format trimesh reads, in ``mm`` or ``m`` (when not given: a mesh more than 3 units across is mm).
  One path per object instance present; the same path twice means two instances of one object. Objects get ids
  1, 2, ... in order of first appearance.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from workbench.errors import InputError
from workbench.io.bop import (
    MAX_DEPTH_SCALE,
    MAX_IMAGE_PIXELS,
    check_depth,
    check_depth_units,
    check_principal_point,
    parse_K,
    read_depth_png,
    read_mesh,
)
from workbench.io.readers import MM, expect_int, expect_number, parse_pose, parse_T, read_json
from workbench.problem.scene import Camera, Frame, ObjectModel

UNITS = {"mm": MM, "m": 1.0}
# Objects on a table are between these sizes (metres); outside them the unit is wrong.
PLAUSIBLE_OBJECT_SIZE = (0.005, 2.0)


def _read_depth(path: Path, depth_scale: float) -> np.ndarray:
    """-> (H, W) float64 metres."""
    if path.suffix.lower() == ".npy":
        if not path.is_file():
            raise InputError(path, "depth file not found")
        try:
            # Mapped first: its size is checked from the header before any number is read (as a PNG's).
            mapped = np.load(path, allow_pickle=False, mmap_mode="r")
        except (ValueError, OSError, EOFError) as e:
            raise InputError(path, f"corrupt .npy file ({e})") from e
        if mapped.size > MAX_IMAGE_PIXELS:
            raise InputError(path, f"holds {mapped.size} numbers ({' x '.join(map(str, mapped.shape))}), more than "
                                   f"any depth sensor gives ({MAX_IMAGE_PIXELS // 10**6} million pixels at most)")
        depth = np.array(mapped)
        real = np.issubdtype(depth.dtype, np.floating) or np.issubdtype(depth.dtype, np.integer)
        if depth.ndim != 2 or not real:
            raise InputError(path, f"depth must be a 2-D array of real numbers (float metres), got {depth.dtype} "
                                   f"{depth.shape}")
        depth = depth.astype(np.float64)
        depth[~np.isfinite(depth) | (depth < 0)] = 0.0
        return depth
    if path.suffix.lower() == ".png":
        return read_depth_png(path) * depth_scale * MM
    raise InputError(path, "depth must be a .png (16-bit) or .npy (float metres) file")


def _camera(intr: dict, path: Path, depth_shape: tuple[int, int]) -> Camera:
    if "K" in intr:
        K = parse_K(intr["K"], path)
    elif all(k in intr for k in ("fx", "fy", "cx", "cy")):
        fx, fy, cx, cy = (expect_number(intr[k], path, k) for k in ("fx", "fy", "cx", "cy"))
        K = parse_K([fx, 0, cx, 0, fy, cy, 0, 0, 1], path)
    else:
        raise InputError(path, 'no intrinsics: give "K" (3x3) or "fx", "fy", "cx", "cy" in pixels')
    height, width = depth_shape
    if "width" in intr or "height" in intr:
        size = (expect_int(intr.get("width", width), path, "width"),
                expect_int(intr.get("height", height), path, "height"))
        if size != (width, height):
            raise InputError(
                path, f"camera is {size[0]}x{size[1]} but the depth image is {width}x{height}: intrinsics for "
                "another resolution? Scale K with the image"
            )
    check_principal_point(K, width, height, path)
    T = None
    if "T_cam_world" in intr:
        T = parse_T(intr["T_cam_world"], path, "T_cam_world")
    elif "cam_R_w2c" in intr or "cam_t_w2c" in intr:
        T = parse_pose(intr.get("cam_R_w2c"), intr.get("cam_t_w2c"), path, "cam_R_w2c/cam_t_w2c")
    return Camera(K, width, height, T)


def _read_object_mesh(path: Path, unit: str | None) -> trimesh.Trimesh:
    """-> trimesh in metres, the unit given or guessed from the size."""
    if unit is not None and unit not in UNITS:
        raise InputError(path, f"mesh unit must be one of {sorted(UNITS)}, got {unit!r}")
    mesh = read_mesh(path, 1.0)
    scale = UNITS[unit] if unit is not None else (MM if mesh.extents.max() > 3.0 else 1.0)
    mesh.apply_scale(scale)
    lo, hi = PLAUSIBLE_OBJECT_SIZE
    if not lo <= mesh.extents.max() <= hi:
        raise InputError(
            path, f"object is {mesh.extents.max():.4g} m across with mesh unit {unit or 'auto'}: give the unit that "
            f"makes it {lo * 1000:g} mm - {hi:g} m"
        )
    return mesh


def load_plain_frame(
    depth_path: Path, intrinsics_path: Path, mesh_paths: list[Path], mesh_unit: str | None = None
) -> tuple[Frame, dict[int, ObjectModel]]:
    """A Frame (object_ids: one per entry of ``mesh_paths``) and its models keyed by obj_id."""
    depth_path, intrinsics_path = Path(depth_path), Path(intrinsics_path)
    intr = read_json(intrinsics_path)
    if not isinstance(intr, dict):
        raise InputError(intrinsics_path, "expected a JSON object with K (or fx, fy, cx, cy)")
    depth_scale = expect_number(intr.get("depth_scale", 1.0), intrinsics_path, "depth_scale")
    if not 0 < depth_scale <= MAX_DEPTH_SCALE:
        raise InputError(intrinsics_path, f"depth_scale must be a positive number up to {MAX_DEPTH_SCALE:g} (mm per "
                                          f"unit), got {depth_scale}")
    depth = _read_depth(depth_path, depth_scale)
    camera = _camera(intr, intrinsics_path, depth.shape)
    check_depth(depth, depth_path, camera)
    if depth_path.suffix.lower() == ".npy":
        check_depth_units(depth, depth_path, "the .npy values as metres", lambda f: f"multiplying the values by {f:g}")
    else:
        check_depth_units(
            depth, depth_path, f"depth_scale {depth_scale:g} (PNG value x depth_scale = mm)",
            lambda f: f"depth_scale {depth_scale * f:g} in {intrinsics_path.name}",
        )
    if not mesh_paths:
        raise InputError(None, "no mesh given: pass one mesh file per object present")

    ids: dict[Path, int] = {}
    models: dict[int, ObjectModel] = {}
    object_ids = []
    for p in map(Path, mesh_paths):
        if p not in ids:
            obj_id = ids[p] = len(ids) + 1
            models[obj_id] = ObjectModel(obj_id, _read_object_mesh(p, mesh_unit), name=p.stem, source=p)
        object_ids.append(ids[p])
    frame = Frame(depth=depth.astype(np.float32), camera=camera, object_ids=object_ids, source=depth_path)
    return frame, models
