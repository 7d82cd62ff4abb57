"""Reading and writing datasets in the BOP format (the results CSV is ``io/results.py``'s).

Format (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md)::

    DATASET/models/models_info.json        {"<obj_id>": {"diameter", "min_x".., "size_x".., "symmetries_discrete",
                                                         "symmetries_continuous"}}
    DATASET/models/obj_XXXXXX.ply          millimetres
    DATASET/<split>/<scene_id:06d>/scene_camera.json   {"<im_id>": {"cam_K", "depth_scale", ["cam_R_w2c", "cam_t_w2c"]}}
    DATASET/<split>/<scene_id:06d>/scene_gt.json       {"<im_id>": [{"obj_id", "cam_R_m2c", "cam_t_m2c"}, ...]}
    DATASET/<split>/<scene_id:06d>/scene_gt_info.json  {"<im_id>": [{"bbox_obj", "visib_fract", ...}, ...]}
    DATASET/<split>/<scene_id:06d>/depth/<im_id:06d>.png   uint16; value x depth_scale = millimetres
    DATASET/<split>/<scene_id:06d>/rgb/<im_id:06d>.png|jpg optional

Rotations are 9 numbers row-major, translations millimetres. In memory everything is metres (``problem/scene.py``).
``DATASET`` may be the dataset root or a split folder (then the models are in its parent). Every problem with
the files raises ``InputError`` naming the file: the typed JSON readers are ``io/readers.py``'s; the image, mesh and
camera readers and checks here (``read_depth_png``, ``read_mesh``, ``parse_K``, ``check_*``) are shared with
``plainframe.py``.
"""

from __future__ import annotations

import io
import json
import logging
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import trimesh
from PIL import Image, UnidentifiedImageError

from workbench.errors import InputError
from workbench.geometry import make_pose
from workbench.io.outputs import replace_file
from workbench.io.readers import (
    MAX_TABLE_DISTANCE,
    MM,
    expect_int,
    expect_list,
    expect_number,
    expect_object,
    parse_pose,
    parse_T,
    read_json,
    read_json_kept,
)
from workbench.meshes.heavy import loading
from workbench.problem.scene import Camera, Frame, ObjectModel

log = logging.getLogger(__name__)
# The warning that an open mesh's mass comes from its hull concerns physics only: a logger of its own, which the
# commands that simulate nothing (score) silence.
hull_log = logging.getLogger(f"{__name__}.hull")
_WARNED_MESHES: set[tuple[str, int, int, str]] = set()  # meshes already warned about, and why (read_mesh)

# Folders that hold the meshes, in order of preference (T-LESS ships models_cad/models_reconst, no models/).
MODEL_DIRS = ("models", "models_cad", "models_eval", "models_reconst")
# A table scene seen by a depth sensor: the median valid depth must lie in this range (metres) or the units are off.
PLAUSIBLE_MEDIAN_DEPTH = (0.15, 6.0)
# Continuous symmetries (bowls, cans) become this many discrete rotations about their axis.
CONTINUOUS_SYMMETRY_STEPS = 36
MAX_FOCAL_IN_IMAGES = 100
MAX_DEPTH_SCALE = 1e4  # millimetres per PNG unit; beyond it 16-bit depth holds nothing but astronomy
# The largest depth sensors give 12 million pixels; at 25 million a frame's depth alone takes 200 MB as float64 (a
# 13000 x 13000 PNG took 4 GB before it was refused), so a larger image is a mistake, refused from its header.
MAX_IMAGE_PIXELS = 25_000_000
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# ----------------------------------------------------------------------------------------------------------------
# Files


def _write_json(path: Path, content: dict) -> None:
    replace_file(path, (json.dumps(content, indent=2) + "\n").encode())


def _merge_json(path: Path, im_id: int, value) -> None:
    """Set key ``str(im_id)`` of the JSON object in ``path`` (created if missing), keys kept in numeric order."""
    content = read_json(path) if path.exists() else {}
    image_ids(content, path)  # a file keyed by anything else is refused, not rewritten
    content[str(im_id)] = value
    _write_json(path, {k: content[k] for k in sorted(content, key=int)})


def _png_bytes(image: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG")
    return buf.getvalue()


def image_size(path: Path, what: str = "image") -> tuple[int, int]:
    """(width, height) of an image from its header alone (a PNG's first 24 bytes, else PIL's lazy open), checked
    against MAX_IMAGE_PIXELS; InputError naming the file otherwise. Cheap enough to check every frame of a sequence
    before the first one runs."""
    if not path.is_file():
        raise InputError(path, f"{what} not found")
    try:
        with open(path, "rb") as f:
            head = f.read(24)
        if head[:8] == PNG_SIGNATURE and head[12:16] == b"IHDR":
            size = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
        else:
            with _opened(path) as im:
                size = im.size
    except OSError as e:
        raise InputError(path, f"cannot be read ({e.strerror or e})") from e
    if size[0] * size[1] > MAX_IMAGE_PIXELS:
        raise InputError(path, f"is {size[0]} x {size[1]} pixels, more than any depth sensor gives "
                               f"({MAX_IMAGE_PIXELS // 10**6} million pixels at most)")
    return size


@contextmanager
def _opened(path: Path) -> Iterator[Image.Image]:
    """PIL's image, opened lazily, its own size limit (a warning, then an error, far above ours) and decoding
    errors turned into InputError naming the file."""
    try:
        with warnings.catch_warnings():
            # A size PIL warns about is refused by image_size anyway: the warning would only repeat it, raw.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(path)
        with im:
            yield im
    except Image.DecompressionBombError as e:
        raise InputError(path, f"has too many pixels ({e})") from e
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise InputError(path, f"corrupt or unreadable image ({e})") from e


def read_image(path: Path, what: str = "image") -> Image.Image:
    """The one image reader every input goes through: the decoded PIL image, its size checked from the header
    before any pixel is decoded (``image_size``), or InputError naming the file."""
    image_size(path, what)
    with _opened(path) as im:
        im.load()
        return im


def read_depth_png(path: Path) -> np.ndarray:
    """A 16-bit single-channel PNG -> (H, W) float64 raw sensor units."""
    im = read_image(path, "depth image")
    if im.mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise InputError(
            path, f"depth must be a 16-bit single-channel PNG, this one is mode {im.mode!r} (an 8-bit or colour "
                  "image?)"
        )
    return np.asarray(im).astype(np.float64)


def read_rgb(path: Path) -> np.ndarray:
    """(H, W, 3) uint8."""
    return np.asarray(read_image(path, "colour image").convert("RGB"))


def image_ids(content, path: Path) -> list[int]:
    """The image ids keying a per-image JSON object (scene_camera.json, scene_gt.json, ...)."""
    expect_object(content, path, "the file")
    bad = [k for k in content if not (k.isascii() and k.isdigit())]
    if bad:
        raise InputError(path, f"keys must be image ids (whole numbers), got {bad[0]!r:.40}")
    return [int(k) for k in content]


# ----------------------------------------------------------------------------------------------------------------
# Validation shared with plainframe.py


def parse_K(values, path: Path) -> np.ndarray:
    """9 numbers (row-major) or a 3x3 nested list -> (3, 3) float64, checked."""
    try:
        K = np.asarray(values, dtype=np.float64).reshape(3, 3)
    except (TypeError, ValueError) as e:
        raise InputError(path, f"cam_K must be 9 numbers (3x3 row-major), got {values!r}") from e
    if not np.all(np.isfinite(K)):
        raise InputError(path, f"cam_K contains NaN or inf: {K.ravel().tolist()}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"cam_K focal lengths must be positive pixels, got fx={K[0, 0]}, fy={K[1, 1]}")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise InputError(path, f"cam_K last row must be [0, 0, 1], got {K[2].tolist()} (transposed?)")
    if abs(K[0, 1]) > 1e-6 * K[0, 0] or K[1, 0] != 0:
        raise InputError(path, f"cam_K must be [fx, 0, cx, 0, fy, cy, 0, 0, 1] (no skew), got {K.ravel().tolist()}")
    return K


def check_depth_units(depth: np.ndarray, path: Path, setting: str, fix: Callable[[float], str]) -> None:
    """Raise when the median valid depth (metres, (H, W)) is implausible for a table scene. ``setting`` names what
    set the units; ``fix(factor)`` says how to change it so that depths are ``factor`` times larger (a power of
    ten that brings the median near 1 m)."""
    median = float(np.median(depth[depth > 0]))
    lo, hi = PLAUSIBLE_MEDIAN_DEPTH
    if lo <= median <= hi:
        return
    factor = float(10.0 ** np.round(-np.log10(median)))
    raise InputError(
        path, f"with {setting} the median depth is {median:.4g} m, but a table scene is 0.2-5 m from the camera; "
        f"{fix(factor)} would put it at {median * factor:.2f} m"
    )


def check_depth(depth: np.ndarray, path: Path, camera: Camera) -> None:
    """Depth (H, W) metres against the camera: size, anything measured. Units are the caller's to check
    (it knows which setting to suggest)."""
    if depth.shape != (camera.height, camera.width):
        raise InputError(
            path,
            f"depth image is {depth.shape[1]}x{depth.shape[0]} but the camera is {camera.width}x{camera.height}: "
            "intrinsics for another resolution? Scale K with the image or use the matching intrinsics",
        )
    if not np.any(depth > 0):
        raise InputError(path, "depth image has no valid pixel (all zero): wrong file or a failed capture")


def check_principal_point(K: np.ndarray, width: int, height: int, path: Path) -> None:
    """BOP cameras carry no image size: a principal point outside the image betrays K of another resolution. A
    focal length over 100 image widths (a field of view under 0.6 degrees) is a typo or another unit."""
    if max(K[0, 0], K[1, 1]) > MAX_FOCAL_IN_IMAGES * max(width, height):
        raise InputError(path, f"cam_K focal lengths fx={K[0, 0]:.4g}, fy={K[1, 1]:.4g} px are implausible for a "
                               f"{width}x{height} image (more than {MAX_FOCAL_IN_IMAGES} image widths)")
    if not (0 <= K[0, 2] <= width and 0 <= K[1, 2] <= height):
        raise InputError(
            path,
            f"cam_K principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) lies outside the {width}x{height} depth image: "
            "intrinsics for another resolution?",
        )
    # Real cameras put it within ~10 % of the centre; a quarter of the image off is K of another resolution (a
    # 640x480 K with a 1280x960 image puts every object tens of centimetres off, silently).
    if abs(K[0, 2] - width / 2) > width / 4 or abs(K[1, 2] - height / 2) > height / 4:
        raise InputError(
            path,
            f"cam_K principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) is far from the centre of the {width}x{height} "
            f"depth image: intrinsics for another resolution (about {2 * K[0, 2]:.0f}x{2 * K[1, 2]:.0f}?)",
        )


def read_mesh(path: Path, scale: float) -> trimesh.Trimesh:
    """Any mesh trimesh reads, times ``scale`` -> metres, vertices merged by position, vertex colours kept.

    Raises InputError when missing, unreadable, empty or degenerate; warns (naming the file, once per process while
    the file is unchanged) when not watertight, because its mass then comes from the convex hull."""
    if not path.is_file():
        raise InputError(path, "mesh file not found")
    with loading(path):  # a heavy model (a 1.3M-face scan: seconds) says so while it loads
        return _read_mesh(path, scale)


def _read_mesh(path: Path, scale: float) -> trimesh.Trimesh:
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh's loaders raise anything from IndexError to KeyError on corrupt files
        raise InputError(path, f"corrupt or unreadable mesh ({type(e).__name__}: {e})") from e
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InputError(path, "mesh has no triangles (a point cloud or an empty file?)")
    vertices = np.asarray(loaded.vertices, dtype=np.float64) * scale
    if not np.all(np.isfinite(vertices)):
        raise InputError(path, "mesh has NaN or inf vertices")
    colors = None
    if loaded.visual.kind == "vertex":
        colors = loaded.visual.vertex_colors
    elif loaded.visual.kind == "texture":
        try:
            colors = loaded.visual.to_color().vertex_colors
        except Exception:  # a missing texture image only loses colour, which nothing but display uses
            colors = None
    # Textured meshes duplicate vertices along UV seams; merging by position makes closed meshes watertight.
    mesh = trimesh.Trimesh(vertices, loaded.faces, vertex_colors=colors, process=True)
    # Flat (zero-volume) meshes cannot be simulated; the test is relative so that unit mistakes reach the caller.
    if len(mesh.faces) == 0 or mesh.extents.min() <= 1e-4 * mesh.extents.max():
        extents = np.round(mesh.extents / scale, 6).tolist()
        raise InputError(path, f"mesh is degenerate (extents {extents} in file units)")
    if not mesh.is_watertight:
        _warn_once(path, "mesh is not watertight; its mass is taken from its convex hull", hull_log)
    elif mesh.volume < 0:
        # Faces wound inside out (normals inward): rendering would cull the wrong side and physics would take a
        # negative volume. A closed mesh has one outside: turned right side out, and said.
        mesh.invert()
        _warn_once(path, "mesh is wound inside out (its faces point inward); it is used turned right side out")
    return mesh


def _warn_once(path: Path, problem: str, logger: logging.Logger = log) -> None:
    """A WARNING naming the mesh file, once per file (as it is now), problem and process: estimating many frames of
    one dataset reloads its models."""
    stat = path.stat()
    seen = (str(path.resolve()), stat.st_size, stat.st_mtime_ns, problem)
    if seen not in _WARNED_MESHES:
        _WARNED_MESHES.add(seen)
        logger.warning("%s: %s", path, problem)


# ----------------------------------------------------------------------------------------------------------------
# Dataset layout


def _is_scene_dir(p: Path) -> bool:
    return p.is_dir() and p.name.isdigit() and (p / "scene_camera.json").is_file()


def _has_scenes(p: Path) -> bool:
    return p.is_dir() and any(_is_scene_dir(c) for c in p.iterdir())


def _split_dir(dataset: Path, split: str | None) -> Path:
    """The folder holding the scene folders."""
    dataset = Path(dataset)
    if not dataset.is_dir():
        raise InputError(dataset, "dataset folder not found")
    if split is not None:
        d = dataset / split
        if not d.is_dir():
            raise InputError(d, f"split folder not found (folders here: {sorted(c.name for c in dataset.iterdir())})")
        return d
    if _has_scenes(dataset):
        return dataset
    if _has_scenes(dataset / "test"):
        return dataset / "test"
    for c in sorted(dataset.iterdir()):
        if _has_scenes(c):
            return c
    raise InputError(dataset, "no scene folders (NNNNNN/scene_camera.json) here or in any split folder below")


def _models_dir(dataset: Path) -> Path:
    dataset = Path(dataset)
    if (dataset / "models_info.json").is_file():
        return dataset
    roots = [dataset, dataset.parent] if _has_scenes(dataset) else [dataset]
    for root in roots:
        for name in MODEL_DIRS:
            if (root / name / "models_info.json").is_file():
                return root / name
    raise InputError(dataset / "models" / "models_info.json", f"file not found (looked in {', '.join(MODEL_DIRS)})")


def _scene_dir(split_dir: Path, scene_id: int) -> Path:
    d = split_dir / f"{scene_id:06d}"
    if not d.is_dir():
        raise InputError(d, f"scene {scene_id} not found")
    return d


def scene_folder(dataset: Path, scene_id: int, split: str | None = None) -> Path:
    """The folder of scene ``scene_id`` (InputError when the dataset or the scene is not there)."""
    return _scene_dir(_split_dir(Path(dataset), split), scene_id)


def _image_file(folder: Path, im_id: int, exts: tuple[str, ...]) -> Path | None:
    for ext in exts:
        p = folder / f"{im_id:06d}{ext}"
        if p.is_file():
            return p
    return None


# ----------------------------------------------------------------------------------------------------------------
# Models


def _model_name(info: dict, path: Path, obj_id: int) -> str:
    """The object's ``name`` in models_info.json (not a BOP field, but some datasets carry one), else
    ``obj_000006``: what the workbench calls the object everywhere."""
    name = info.get("name") if isinstance(info, dict) else None
    if name is None:
        return f"obj_{obj_id:06d}"
    if not isinstance(name, str) or not name.strip():
        raise InputError(path, f"object {obj_id}: \"name\" must be a non-empty string, got {name!r}")
    return name.strip()


def load_symmetries(dataset: Path, obj_ids: list[int], steps: int) -> dict[int, np.ndarray]:
    """The symmetries of the dataset's models ``obj_ids`` (models_info.json), each continuous one sampled at
    ``steps`` rotations: obj_id -> (S, 4, 4) metres, identity first. Scoring samples finer than the estimator."""
    info_path = _models_dir(Path(dataset)) / "models_info.json"
    info = read_json(info_path)
    known = sorted(_object_ids(info, info_path))
    out = {}
    for obj_id in obj_ids:
        if str(obj_id) not in info:
            raise InputError(info_path, f"unknown obj_id {obj_id}; this dataset has objects {known}")
        out[obj_id] = _symmetries(info[str(obj_id)], info_path, obj_id, steps)
    return out


def _symmetries(info: dict, path: Path, obj_id: int, steps: int = CONTINUOUS_SYMMETRY_STEPS) -> np.ndarray:
    """models_info entry -> (S, 4, 4) metres, identity first: discrete ones, each combined with the continuous
    ones discretised into ``steps`` rotations (as bop_toolkit's get_symmetry_transformations)."""
    what = f"object {obj_id}"
    expect_object(info, path, what)
    discrete = [np.eye(4)]
    for values in expect_list(info.get("symmetries_discrete", []), path, f"{what} symmetries_discrete"):
        discrete.append(parse_T(values, path, f"{what} symmetries_discrete", t_unit=MM))
    continuous = [np.eye(4)]
    for sym in expect_list(info.get("symmetries_continuous", []), path, f"{what} symmetries_continuous"):
        sym = expect_object(sym, path, f"{what} symmetries_continuous entry")
        if "axis" not in sym:
            raise InputError(path, f"{what} symmetries_continuous: an entry has no axis")
        axis = _vector3(sym["axis"], path, f"{what} symmetries_continuous axis")
        offset = _vector3(sym.get("offset", [0.0, 0.0, 0.0]), path, f"{what} symmetries_continuous offset") * MM
        if np.linalg.norm(axis) < 1e-9:
            raise InputError(path, f"{what} symmetries_continuous axis must not be zero")
        axis = axis / np.linalg.norm(axis)
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        for a in np.arange(1, steps) * 2 * np.pi / steps:
            R = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
            continuous.append(make_pose(R, offset - R @ offset))
    return np.stack([c @ d for d in discrete for c in continuous])


def _vector3(value, path: Path, what: str) -> np.ndarray:
    values = expect_list(value, path, what)
    if len(values) != 3:
        raise InputError(path, f"{what} must be 3 numbers, got {len(values)}")
    return np.array([expect_number(v, path, what) for v in values])


def load_models(
    dataset: Path, obj_ids: list[int] | None = None, density: float = 1000.0, friction: float = 0.75
) -> dict[int, ObjectModel]:
    """The object models (metres) of a BOP dataset, all or those in ``obj_ids``; keyed by obj_id."""
    models_dir = _models_dir(Path(dataset))
    info_path = models_dir / "models_info.json"
    info = read_json(info_path)
    known = sorted(_object_ids(info, info_path))
    wanted = known if obj_ids is None else list(dict.fromkeys(int(i) for i in obj_ids))
    models = {}
    for obj_id in wanted:
        if str(obj_id) not in info:
            raise InputError(info_path, f"unknown obj_id {obj_id}; this dataset has objects {known}")
        path = models_dir / f"obj_{obj_id:06d}.ply"
        mesh = read_mesh(path, MM)
        if not 0.003 <= mesh.extents.max() <= 3.0:
            hint = ("is this file in metres?" if mesh.extents.max() < 0.003 else
                    "far larger than an object on a table: is it in micrometres, or scaled up?")
            raise InputError(
                path, f"object is {mesh.extents.max() * 1000:g} mm across; BOP models are in millimetres ({hint})"
            )
        models[obj_id] = ObjectModel(
            obj_id=obj_id,
            mesh=mesh,
            name=_model_name(info[str(obj_id)], info_path, obj_id),
            density=density,
            friction=friction,
            symmetries=_symmetries(info[str(obj_id)], info_path, obj_id),
            source=path,
        )
    return models


def model_ids(dataset: Path) -> set[int]:
    """The obj_ids of a dataset's models (its models_info.json)."""
    info_path = _models_dir(Path(dataset)) / "models_info.json"
    return set(_object_ids(read_json(info_path), info_path))


def _object_ids(info, path: Path) -> list[int]:
    """The obj_ids keying models_info.json."""
    expect_object(info, path, "models_info.json (keyed by obj_id)")
    bad = [k for k in info if not (k.isascii() and k.isdigit())]
    if bad:
        raise InputError(path, f"keys must be object ids (whole numbers), got {bad[0]!r:.40}")
    return [int(k) for k in info]


def save_models(
    dataset: Path, meshes: dict[int, trimesh.Trimesh], symmetries: dict[int, np.ndarray] | None = None,
    symmetries_continuous: dict[int, list[dict]] | None = None,
) -> None:
    """Write meshes (metres) as DATASET/models/obj_XXXXXX.ply (mm) and models_info.json.

    ``symmetries``: obj_id -> (S, 4, 4) metres; identity entries are not written (BOP lists only the others).
    ``symmetries_continuous``: obj_id -> [{"axis": (3,), "offset": (3,) mm}], written as BOP's
    ``symmetries_continuous`` (a can: axis [0, 0, 1], offset [0, 0, 0])."""
    models_dir = Path(dataset) / "models"
    info_path = models_dir / "models_info.json"
    info = read_json(info_path) if info_path.exists() else {}
    _object_ids(info, info_path)  # a malformed file is refused, not rewritten
    for obj_id, mesh in meshes.items():
        mm = mesh.copy()
        mm.apply_scale(1.0 / MM)
        replace_file(models_dir / f"obj_{obj_id:06d}.ply", mm.export(file_type="ply"))
        hull = mm.convex_hull.vertices
        diameter = float(np.max(np.linalg.norm(hull[:, None] - hull[None], axis=-1)))
        lo, size = mm.bounds[0], mm.extents
        entry = {"diameter": diameter}
        entry.update({f"min_{a}": float(lo[i]) for i, a in enumerate("xyz")})
        entry.update({f"size_{a}": float(size[i]) for i, a in enumerate("xyz")})
        syms = [] if symmetries is None else symmetries.get(obj_id, [])
        disc = []
        for S in np.asarray(syms, dtype=np.float64).reshape(-1, 4, 4):
            if np.allclose(S, np.eye(4)):
                continue
            S = S.copy()
            S[:3, 3] /= MM
            disc.append(S.ravel().tolist())
        if disc:
            entry["symmetries_discrete"] = disc
        continuous = [] if symmetries_continuous is None else symmetries_continuous.get(obj_id, [])
        if continuous:
            entry["symmetries_continuous"] = [
                {"axis": [float(v) for v in c["axis"]], "offset": [float(v) for v in c.get("offset", (0, 0, 0))]}
                for c in continuous
            ]
        info[str(obj_id)] = entry
    _write_json(info_path, {k: info[k] for k in sorted(info, key=int)})


def copy_models(source: Path, dataset: Path, obj_ids: list[int]) -> None:
    """Copy models ``obj_ids`` of the BOP dataset (or models folder) ``source`` into DATASET/models as they are:
    their files and models_info.json entries (symmetries as ``source`` declares them), added to any already
    there."""
    src = _models_dir(Path(source))
    src_info = read_json(src / "models_info.json")
    models_dir = Path(dataset) / "models"
    info_path = models_dir / "models_info.json"
    info = read_json(info_path) if info_path.exists() else {}
    _object_ids(info, info_path)  # a malformed file is refused, not rewritten
    for obj_id in obj_ids:
        name = f"obj_{obj_id:06d}.ply"
        replace_file(models_dir / name, (src / name).read_bytes())
        info[str(obj_id)] = src_info[str(obj_id)]
    _write_json(info_path, {k: info[k] for k in sorted(info, key=int)})


# ----------------------------------------------------------------------------------------------------------------
# Frames


def list_frames(dataset: Path, split: str | None = None) -> list[tuple[int, int]]:
    """All (scene_id, im_id) of a split, sorted."""
    split_dir = _split_dir(Path(dataset), split)
    frames = []
    for scene in sorted(c for c in split_dir.iterdir() if _is_scene_dir(c)):
        frames.extend((int(scene.name), im_id) for im_id in image_ids(read_json(scene / "scene_camera.json"),
                                                                       scene / "scene_camera.json"))
    return sorted(frames)


def _targets(dataset_root: Path, scene_id: int, im_id: int) -> list[int] | None:
    """Object ids from a BOP test_targets_*.json (test splits whose ground truth is withheld)."""
    for path in sorted(dataset_root.glob("test_targets_*.json")):
        rows = expect_list(read_json(path), path, "the file (a list of targets)")
        ids = []
        for row in rows:
            row = expect_object(row, path, "a target")
            if row.get("scene_id") == scene_id and row.get("im_id") == im_id:
                if "obj_id" not in row:
                    raise InputError(path, f"scene {scene_id} image {im_id}: a target has no obj_id")
                count = expect_int(row.get("inst_count", 1), path, "inst_count")
                if not 1 <= count <= 100:
                    raise InputError(path, f"inst_count must be from 1 to 100, got {count}")
                ids.extend([expect_int(row["obj_id"], path, "obj_id")] * count)
        if ids:
            return ids
    return None


def _camera_json_size(split_dir: Path) -> tuple[Path, int, int] | None:
    """(file, width, height) of the dataset-level camera file for this split, if there is one."""
    suffix = split_dir.name.split("_", 1)[1] if "_" in split_dir.name else ""
    path = split_dir.parent / (f"camera_{suffix}.json" if suffix else "camera.json")
    if not path.is_file():
        return None
    cam = expect_object(read_json(path), path, "the file")
    if "width" not in cam or "height" not in cam:
        return None
    return path, expect_int(cam["width"], path, "width"), expect_int(cam["height"], path, "height")


def load_frame(
    dataset: Path, scene_id: int, im_id: int, split: str | None = None, object_ids: list[int] | None = None
) -> Frame:
    """One frame. ``object_ids`` (repeats for several instances) default to those of scene_gt.json, else of the
    dataset's test_targets_*.json. ``gt_T_cam_obj`` (K, 4, 4) follows ``object_ids`` (instances of one object in
    the order of scene_gt.json); rows of objects without ground truth are NaN; None when there is no scene_gt.json."""
    dataset = Path(dataset)
    split_dir = _split_dir(dataset, split)
    scene_dir = _scene_dir(split_dir, scene_id)
    cam_path = scene_dir / "scene_camera.json"
    cams = read_json_kept(cam_path)  # read, never changed here
    ids = sorted(image_ids(cams, cam_path))
    if str(im_id) not in cams:
        span = f"{ids[0]}..{ids[-1]}" if ids else "none"
        raise InputError(cam_path, f"image {im_id} is not in scene {scene_id} (image ids {span}, {len(ids)} images)")
    cam = expect_object(cams[str(im_id)], cam_path, f"image {im_id}")
    if "cam_K" not in cam:
        raise InputError(cam_path, f"image {im_id} has no cam_K (the 3x3 intrinsics, 9 numbers row-major)")
    K = parse_K(cam["cam_K"], cam_path)
    depth_scale = expect_number(cam.get("depth_scale", 1.0), cam_path, f"image {im_id} depth_scale")
    if not 0 < depth_scale <= MAX_DEPTH_SCALE:
        raise InputError(cam_path, f"image {im_id}: depth_scale must be a positive number up to {MAX_DEPTH_SCALE:g} "
                                   f"(mm per PNG unit), got {depth_scale}")
    T_cam_world = None
    if "cam_R_w2c" in cam and "cam_t_w2c" in cam:
        T_cam_world = parse_pose(cam["cam_R_w2c"], cam["cam_t_w2c"], cam_path, f"image {im_id} cam_R_w2c/cam_t_w2c")
        distance = float(np.abs(T_cam_world[:3, 3]).max())
        if distance > MAX_TABLE_DISTANCE:
            raise InputError(cam_path, f"image {im_id} cam_t_w2c puts the table frame {distance:.4g} m from the camera "
                                       f"(at most {MAX_TABLE_DISTANCE:g} m): translations are in millimetres")

    depth_path = scene_dir / "depth" / f"{im_id:06d}.png"
    depth = read_depth_png(depth_path) * depth_scale * MM
    height, width = depth.shape
    sized = _camera_json_size(split_dir)
    if sized is not None and (sized[1], sized[2]) != (width, height):
        raise InputError(
            depth_path, f"depth image is {width}x{height} but {sized[0].name} says {sized[1]}x{sized[2]}"
        )
    check_principal_point(K, width, height, cam_path)
    camera = Camera(K, width, height, T_cam_world)
    check_depth(depth, depth_path, camera)
    check_depth_units(
        depth, cam_path, f"image {im_id} depth_scale {depth_scale:g} (PNG value x depth_scale = mm)",
        lambda factor: f"depth_scale {depth_scale * factor:g}",
    )

    gt_path = scene_dir / "scene_gt.json"
    gt_entries = None
    if gt_path.is_file():
        gt_all = read_json_kept(gt_path)  # read, never changed here
        image_ids(gt_all, gt_path)
        if str(im_id) not in gt_all:
            raise InputError(gt_path, f"image {im_id} has no ground-truth entry")
        gt_entries = expect_list(gt_all[str(im_id)], gt_path, f"image {im_id}")
        for g in gt_entries:
            g = expect_object(g, gt_path, f"image {im_id}: an object entry")
            for key in ("obj_id", "cam_R_m2c", "cam_t_m2c"):
                if key not in g:
                    raise InputError(gt_path, f"image {im_id}: an object entry has no {key}")
            expect_int(g["obj_id"], gt_path, f"image {im_id} obj_id")
    if object_ids is None:
        if gt_entries is not None:
            object_ids = [g["obj_id"] for g in gt_entries]
        else:
            object_ids = _targets(split_dir.parent, scene_id, im_id)
            if object_ids is None:
                raise InputError(
                    scene_dir, f"image {im_id}: no scene_gt.json or test_targets_*.json says which objects are "
                    "present; name them (`workbench estimate --objects ID ...`)"
                )
    object_ids = [int(i) for i in object_ids]
    if not object_ids:
        raise InputError(gt_path if gt_entries is not None else scene_dir, f"image {im_id}: no objects to estimate")
    try:
        info_path = _models_dir(dataset) / "models_info.json"
    except InputError:
        info_path = None  # a dataset without models may still be read for its frames
    if info_path is not None:
        known = set(_object_ids(read_json_kept(info_path), info_path))
        unknown = sorted(set(object_ids) - known)
        if unknown:
            raise InputError(info_path, f"unknown obj_id {unknown}; this dataset has objects {sorted(known)}")

    gt = None
    if gt_entries is not None:
        gt = np.full((len(object_ids), 4, 4), np.nan)
        used = [False] * len(gt_entries)
        for k, obj_id in enumerate(object_ids):
            for j, g in enumerate(gt_entries):
                if not used[j] and g["obj_id"] == obj_id:
                    gt[k] = parse_pose(g["cam_R_m2c"], g["cam_t_m2c"], gt_path, f"image {im_id} object {obj_id}")
                    used[j] = True
                    break

    rgb = None
    rgb_path = _image_file(scene_dir / "rgb", im_id, (".png", ".jpg", ".jpeg"))
    if rgb_path is not None:
        rgb = read_rgb(rgb_path)
        if rgb.shape[:2] != depth.shape:
            raise InputError(rgb_path, f"colour image is {rgb.shape[1]}x{rgb.shape[0]}, depth is {width}x{height}")
    return Frame(
        depth=depth.astype(np.float32),
        camera=camera,
        object_ids=object_ids,
        scene_id=scene_id,
        im_id=im_id,
        gt_T_cam_obj=gt,
        rgb=rgb,
        source=depth_path,
    )


def R_t_mm(T: np.ndarray) -> tuple[list[float], list[float]]:
    """A pose (4, 4) metres -> (R 9 numbers row-major, t 3 numbers mm), as scene_gt.json and the results CSV keep it."""
    T = np.asarray(T, dtype=np.float64)
    return T[:3, :3].ravel().tolist(), (T[:3, 3] / MM).tolist()


def save_frame(
    dataset: Path,
    scene_id: int,
    im_id: int,
    depth: np.ndarray,
    K: np.ndarray,
    T_cam_world: np.ndarray | None = None,
    gt: list[tuple[int, np.ndarray]] | None = None,
    gt_info: list[dict] | None = None,
    depth_scale: float = 0.1,
    split: str = "test",
    rgb: np.ndarray | None = None,
) -> None:
    """Write one frame, merged into the scene's JSON files. ``depth``: (H, W) metres, 0 = no reading; stored as
    round(depth_mm / depth_scale) in uint16, so ``depth_scale`` 0.1 reaches 6.5 m. ``gt``: (obj_id, T_cam_obj
    metres) per instance. ``rgb``: (H, W, 3) uint8."""
    scene_dir = Path(dataset) / split / f"{scene_id:06d}"
    depth = np.asarray(depth, dtype=np.float64)
    if not np.all(np.isfinite(depth)) or depth.min() < 0:
        raise InputError(scene_dir, "depth must be finite metres >= 0 (0 = no reading)")
    units = np.round(depth / MM / depth_scale)
    if units.max() > np.iinfo(np.uint16).max:
        raise InputError(
            scene_dir, f"depth up to {depth.max():.2f} m does not fit 16 bits at depth_scale {depth_scale}; "
            f"use depth_scale >= {depth.max() / MM / 65535:.3g}"
        )
    replace_file(scene_dir / "depth" / f"{im_id:06d}.png", _png_bytes(units.astype(np.uint16)))
    if rgb is not None:
        replace_file(scene_dir / "rgb" / f"{im_id:06d}.png", _png_bytes(np.asarray(rgb, dtype=np.uint8)))
    cam = {"cam_K": np.asarray(K, dtype=np.float64).ravel().tolist(), "depth_scale": float(depth_scale)}
    if T_cam_world is not None:
        cam["cam_R_w2c"], cam["cam_t_w2c"] = R_t_mm(T_cam_world)
    _merge_json(scene_dir / "scene_camera.json", im_id, cam)
    if gt is not None:
        entries = []
        for obj_id, T in gt:
            R, t = R_t_mm(T)
            entries.append({"cam_R_m2c": R, "cam_t_m2c": t, "obj_id": int(obj_id)})
        _merge_json(scene_dir / "scene_gt.json", im_id, entries)
    if gt_info is not None:
        _merge_json(scene_dir / "scene_gt_info.json", im_id, gt_info)
