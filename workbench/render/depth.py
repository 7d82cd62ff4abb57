"""Batched offscreen depth rendering of particle scenes.

Many particles (one scene each: the same K object meshes in different poses) are drawn as tiles of one large
framebuffer with instanced drawing, one ``glDrawElementsInstanced`` per mesh per pass, and read back straight
into the output array, one ``glReadPixels`` per column of tiles. That shares the fixed per-draw cost (context
switch, readback round trip) of a software renderer among hundreds of particles.

Output: float32 camera-z depth in metres (OpenCV camera frame), 0 where no object is seen. Only the objects are
drawn: no table, no background. Pixel (u, v) holds the depth along the ray through image point (u, v) of K
(OpenCV: K maps a 3-D point to integer coordinates at pixel centres); no multisampling.

The OpenGL backend is chosen **once per process**: PyOpenGL binds its GL library when ``OpenGL.GL`` is first
imported, so whatever imports it first (the first ``DepthRenderer``, or pyrender) fixes it. Importing this module
sets ``PYOPENGL_PLATFORM`` (unless already set) from ``WORKBENCH_GL=osmesa|egl`` or, without it, to ``egl`` when
an NVIDIA GPU is present and ``osmesa`` otherwise. ``RenderConfig.backend`` may pick another backend only while
no OpenGL has been loaded in the process. Never fork after a renderer exists (the child hangs): use ``spawn``
workers, each creating its own ``DepthRenderer``.
"""

from __future__ import annotations

import ctypes
import hashlib
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from workbench.errors import InputError
from workbench.meshes import cache
from workbench.meshes.heavy import working_mesh
from workbench.problem.scene import Camera

BACKENDS = ("osmesa", "egl")

# Clip planes of the z-test only; the depth written is linear camera z, so they bound range, not precision.
# A 32-bit float depth buffer separates surfaces 0.1 mm apart at 3 m with these.
Z_NEAR = 0.05
Z_FAR = 20.0


def default_backend() -> str:
    """The backend for a process that does not ask for one: ``WORKBENCH_GL``, else ``egl`` if an NVIDIA GPU
    is present, else ``osmesa``."""
    name = os.environ.get("WORKBENCH_GL", "").strip().lower()
    if name:
        if name not in BACKENDS:
            raise InputError("WORKBENCH_GL", f"must be one of {', '.join(BACKENDS)}, not {name!r}")
        return name
    return "egl" if os.path.exists("/dev/nvidia0") else "osmesa"


# Set before anything imports OpenGL so that a later `import pyrender` elsewhere agrees with the renderer.
os.environ.setdefault("PYOPENGL_PLATFORM", default_backend())


@dataclass
class RenderConfig:
    """``backend``: "auto" (the process's backend, see the module docstring) | "osmesa" | "egl".
    ``max_framebuffer``: pixels per side of the tiled framebuffer; larger batches take several passes.
    ``max_depth_error``: metres; each mesh is drawn as its coarsest quadric decimation whose surface stays this
    close to the full mesh (``render_mesh``), 0 draws the full meshes. ``cull_back_faces``: skip the back faces of
    closed, outward-wound meshes (``closed_outward``); the depth is the same, a third cheaper to draw."""

    backend: str = "auto"
    max_framebuffer: int = 2048
    max_depth_error: float = 1e-3
    cull_back_faces: bool = True


# Decimation halves the face count until the surface leaves the bound: a few decimations (~50 ms each for 16k
# faces), never below _MIN_FACES.
_MIN_FACES = 64
_DEVIATION_PERCENTILE = 99.0
_SAMPLES = 20000
_MESH_CACHE: dict[str, trimesh.Trimesh] = {}


def default_cache_dir() -> Path:
    """Where decimated render meshes are kept between runs: ``$XDG_CACHE_HOME/workbench/render``."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "workbench" / "render"


def depth_deviation(full: trimesh.Trimesh, simple: trimesh.Trimesh) -> float:
    """Metres: the ``_DEVIATION_PERCENTILE`` percentile of the depth difference between two meshes along
    ``_SAMPLES`` seeded rays from all around (from a sphere of twice the mesh's size towards random points of its
    bounding box), over the rays that hit both. Rays that hit only one lie on a silhouette, where a pixel
    straddles an edge at any resolution."""
    import open3d as o3d

    rng = np.random.default_rng(0)
    lo, hi = full.bounds
    centre, size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    towards = rng.uniform(lo, hi, size=(_SAMPLES, 3))
    origins = rng.normal(size=(_SAMPLES, 3))
    origins = centre + 2.0 * size * origins / np.linalg.norm(origins, axis=1, keepdims=True)
    directions = towards - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    rays = o3d.core.Tensor(np.concatenate([origins, directions], axis=1).astype(np.float32))

    def hit(mesh):
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                            o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))
        return scene.cast_rays(rays)["t_hit"].numpy()

    a, b = hit(full), hit(simple)
    both = np.isfinite(a) & np.isfinite(b)
    if not both.any():
        return float("inf")
    return float(np.percentile(np.abs(a[both] - b[both]), _DEVIATION_PERCENTILE))


def render_mesh(mesh: trimesh.Trimesh, max_error: float = 1e-3, cache_dir: str | os.PathLike | None = None
                ) -> trimesh.Trimesh:
    """The mesh to draw for ``mesh`` (metres): its coarsest quadric decimation (open3d) found whose
    ``depth_deviation`` from the full mesh is at most ``max_error``; the full mesh itself
    when none is, or when ``max_error`` is 0. Cached in memory and under ``cache_dir`` (default
    ``default_cache_dir()``), keyed by the mesh and the bound. The full mesh stays the one for display and
    metrics."""
    if max_error <= 0 or len(mesh.faces) <= 2 * _MIN_FACES:
        return mesh
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    h.update(repr((max_error, _MIN_FACES, _DEVIATION_PERCENTILE, _SAMPLES, "rays", "checked")).encode())
    key = h.hexdigest()
    if key in _MESH_CACHE:
        return _MESH_CACHE[key]
    path = Path(cache_dir or default_cache_dir()) / f"{key}.npz"
    simple = cache.load(path, _mesh_from_arrays)
    if simple is None:
        simple = _decimate_within(mesh, max_error)
        cache.save(path, {"vertices": simple.vertices, "faces": simple.faces})
    _MESH_CACHE[key] = simple
    return simple


def _mesh_from_arrays(data: dict[str, np.ndarray]) -> trimesh.Trimesh:
    """A cached render mesh's arrays -> the mesh; ValueError when they do not make one."""
    vertices, faces = np.asarray(data["vertices"], dtype=np.float64), np.asarray(data["faces"])
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3 or not len(faces):
        raise ValueError("it holds no triangle mesh")
    if not np.isfinite(vertices).all() or faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError("its mesh has non-finite vertices or faces indexing no vertex")
    return trimesh.Trimesh(vertices, faces, process=False)


def _decimate_within(mesh: trimesh.Trimesh, max_error: float) -> trimesh.Trimesh:
    """Halve the face count while the result stays within the bound, then bisect between the last face count
    that passed and the first that failed (3 more decimations)."""
    import open3d as o3d

    work = working_mesh(mesh)  # a mesh of over HEAVY_FACES faces: decimated from its 100k-face decimation
    source = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(work.vertices, dtype=np.float64)),
                                       o3d.utility.Vector3iVector(np.asarray(work.faces, dtype=np.int32)))

    def within(target: int) -> trimesh.Trimesh | None:
        simple = source.simplify_quadric_decimation(target_number_of_triangles=target)
        candidate = trimesh.Trimesh(np.asarray(simple.vertices), np.asarray(simple.triangles), process=False)
        ok = len(candidate.faces) > 0 and depth_deviation(mesh, candidate) <= max_error
        return candidate if ok else None

    best, good, bad = mesh, len(work.faces), None
    if work is not mesh and depth_deviation(mesh, work) <= max_error:
        best = work
    target = len(work.faces) // 2
    while target >= _MIN_FACES:
        candidate = within(target)
        if candidate is None:
            bad = target
            break
        best, good = candidate, target
        target //= 2
    for _ in range(3 if bad is not None else 0):
        target = (good + bad) // 2
        candidate = within(target)
        if candidate is None:
            bad = target
        else:
            best, good = candidate, target
    return best


_VERTEX_SHADER = """
#version 330 core
layout(location = 0) in vec3 position;
layout(location = 1) in mat4 T_cam_obj;  // per instance, locations 1-4
uniform mat4 projection;                 // OpenCV camera frame -> clip space of tile 0
uniform ivec2 tile_size;                 // (W, H) pixels
uniform int rows;                        // tiles per framebuffer column
uniform vec2 framebuffer_size;           // pixels
uniform int first_instance;              // the tile of this draw's first instance (a run of the pass's tiles)
out float z_cam;
void main() {
    vec4 p = T_cam_obj * vec4(position, 1.0);
    // Column-major tiles: each column of tiles reads back as consecutive (H, W) images.
    int tile = first_instance + gl_InstanceID;
    ivec2 cell = ivec2(tile / rows, tile % rows);
    vec2 offset = 2.0 * vec2(cell * tile_size) / framebuffer_size;  // NDC shift from tile 0 to this tile
    vec2 lo = offset - 1.0;                                          // this tile's rectangle in NDC
    vec2 hi = lo + 2.0 * vec2(tile_size) / framebuffer_size;
    gl_Position = projection * p;
    // clip w == camera z, so adding offset * z shifts the projected image by offset in NDC.
    gl_Position.xy += offset * p.z;
    // Clip each particle to its own tile so that it never reaches a neighbour's. Clipping planes, not a
    // fragment discard: llvmpipe renders the batch ~20 % faster (0.11 vs 0.14 ms/particle, 4 boxes).
    gl_ClipDistance[0] = gl_Position.x - lo.x * gl_Position.w;
    gl_ClipDistance[1] = hi.x * gl_Position.w - gl_Position.x;
    gl_ClipDistance[2] = gl_Position.y - lo.y * gl_Position.w;
    gl_ClipDistance[3] = hi.y * gl_Position.w - gl_Position.y;
    z_cam = p.z;
}
"""

_FRAGMENT_SHADER = """
#version 330 core
in float z_cam;
layout(location = 0) out float depth;
void main() {
    depth = z_cam;
}
"""


def closed_outward(mesh: trimesh.Trimesh) -> bool:
    """Whether ``mesh`` is closed with its faces wound outward: then no back face is ever the nearest surface, and
    culling back faces (a third off a software render) leaves the depth unchanged. An open or inside-out mesh
    can show a back face through its hole, so it is drawn whole."""
    return bool(mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0)


def projection_matrix(K: np.ndarray, fb_width: int, fb_height: int) -> np.ndarray:
    """OpenCV camera frame -> GL clip space for the tile at the framebuffer's origin. -> (4, 4) float32.

    GL rasterises pixel column i at window x = i + 0.5, so window x = u + 0.5 where u = K's image x; likewise
    for y. The image is drawn with v increasing along GL's window y, so framebuffer memory rows come out in
    image row order without a flip. Clip w = camera z.
    """
    fx, s, cx = K[0]
    fy, cy = K[1, 1], K[1, 2]
    a = (Z_FAR + Z_NEAR) / (Z_FAR - Z_NEAR)
    b = -2.0 * Z_FAR * Z_NEAR / (Z_FAR - Z_NEAR)
    return np.array(
        [
            [2 * fx / fb_width, 2 * s / fb_width, 2 * (cx + 0.5) / fb_width - 1, 0],
            [0, 2 * fy / fb_height, 2 * (cy + 0.5) / fb_height - 1, 0],
            [0, 0, a, b],
            [0, 0, 1, 0],
        ],
        dtype=np.float32,
    )


def _bound_backend() -> str | None:
    """The backend PyOpenGL has already bound in this process, or None if it has bound none yet."""
    platform = sys.modules.get("OpenGL.platform")
    if platform is None:
        return None
    name = type(platform.PLATFORM).__name__
    return {"OSMesaPlatform": "osmesa", "EGLPlatform": "egl"}.get(name, name)


def _bind_backend(requested: str) -> str:
    """Fix this process's backend (see module docstring) and return it."""
    if requested not in ("auto",) + BACKENDS:
        raise InputError("RenderConfig.backend", f"must be auto, {', '.join(BACKENDS)}; not {requested!r}")
    bound = _bound_backend()
    if bound is None:
        env = os.environ.get("PYOPENGL_PLATFORM", "")
        chosen = requested if requested != "auto" else env if env in BACKENDS else default_backend()
        os.environ["PYOPENGL_PLATFORM"] = chosen
        return chosen
    if bound not in BACKENDS:
        raise InputError(
            "PYOPENGL_PLATFORM",
            f"OpenGL was loaded for {bound}, the renderer needs osmesa or egl: set WORKBENCH_GL before starting",
        )
    if requested not in ("auto", bound):
        raise InputError(
            "RenderConfig.backend",
            f"this process already loaded OpenGL for {bound}; the backend is chosen once per process: "
            f"set WORKBENCH_GL={requested} before starting it, or render in a spawned worker",
        )
    return bound


def _create_platform(backend: str):
    """A pyrender platform with a current GL 3.3+ core context. Its own window-system buffer is unused (1x1)."""
    try:
        if backend == "egl":
            from pyrender.platforms.egl import EGLPlatform

            platform = EGLPlatform(1, 1)
        else:
            from pyrender.platforms.osmesa import OSMesaPlatform

            platform = OSMesaPlatform(1, 1)
        platform.init_context()
        platform.make_current()
    except Exception as e:  # the libraries raise a variety of types for "no such device/driver"
        raise RuntimeError(f"could not create an {backend} OpenGL context: {e!r}") from e
    return platform


def _compile_program(GL, vertex_source: str, fragment_source: str) -> int:
    program = GL.glCreateProgram()
    shaders = []
    for kind, source in ((GL.GL_VERTEX_SHADER, vertex_source), (GL.GL_FRAGMENT_SHADER, fragment_source)):
        shader = GL.glCreateShader(kind)
        GL.glShaderSource(shader, source)
        GL.glCompileShader(shader)
        if not GL.glGetShaderiv(shader, GL.GL_COMPILE_STATUS):
            raise RuntimeError(f"shader compilation failed: {GL.glGetShaderInfoLog(shader).decode()}")
        GL.glAttachShader(program, shader)
        shaders.append(shader)
    GL.glLinkProgram(program)
    if not GL.glGetProgramiv(program, GL.GL_LINK_STATUS):
        raise RuntimeError(f"shader link failed: {GL.glGetProgramInfoLog(program).decode()}")
    for shader in shaders:
        GL.glDeleteShader(shader)
    return program


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """The runs of consecutive True in ``mask`` (n,) bool -> [(first, last + 1), ...] in order."""
    edges = np.flatnonzero(np.diff(np.concatenate([[False], mask, [False]]).astype(np.int8)))
    return list(zip(edges[0::2].tolist(), edges[1::2].tolist()))


def _vertex_attrib_pointer(*args) -> None:
    """``glVertexAttribPointer`` without PyOpenGL's wrapper, which keeps every pointer it is given alive in a
    per-context store: a third of a small batch's render time on llvmpipe, for an offset into a bound buffer that
    needs no keeping."""
    from OpenGL.raw.GL.VERSION.GL_2_0 import glVertexAttribPointer

    glVertexAttribPointer(*args)


class DepthRenderer:
    """Renders batches of particle scenes of fixed meshes from one camera.

    ``camera``: K, width, height and ``T_cam_world`` (table frame -> camera), usually a region of interest
    (``Camera.cropped`` / ``Camera.scaled``). ``meshes``: the K objects in metres, each in its own frame; they
    are drawn as ``render_mesh`` of each (``self.meshes``), within ``config.max_depth_error`` of them.
    Holds a GL context: call ``close()`` (or use as a context manager). Not thread-safe.
    """

    def __init__(self, camera: Camera, meshes: list[trimesh.Trimesh], config: RenderConfig = RenderConfig()):
        if camera.T_cam_world is None:
            raise InputError("camera", "the camera pose T_cam_world is unknown; estimate the table first")
        if not meshes:
            raise ValueError("DepthRenderer needs at least one mesh")
        self.camera = camera
        self.n_objects = len(meshes)
        self._T_cam_world = np.asarray(camera.T_cam_world, dtype=np.float64)
        self._width, self._height = int(camera.width), int(camera.height)

        if config.max_framebuffer < max(self._width, self._height):
            raise InputError(
                "RenderConfig.max_framebuffer",
                f"{config.max_framebuffer} px is smaller than the {self._width}x{self._height} camera",
            )

        self.backend = _bind_backend(config.backend)
        self._platform = _create_platform(self.backend)
        from OpenGL import GL

        # llvmpipe allows 16384; no real ROI camera comes near the limit, so clamping is all that is needed.
        viewport_limit = GL.glGetIntegerv(GL.GL_MAX_VIEWPORT_DIMS)
        limit = int(min(GL.glGetIntegerv(GL.GL_MAX_RENDERBUFFER_SIZE), *viewport_limit))
        side = min(config.max_framebuffer, limit)
        self._max_columns = side // self._width
        self._max_rows = side // self._height
        self._fb_size = (0, 0)  # pixels (w, h)

        self._program = _compile_program(GL, _VERTEX_SHADER, _FRAGMENT_SHADER)
        self._uniforms = {
            name: GL.glGetUniformLocation(self._program, name)
            for name in ("projection", "tile_size", "rows", "framebuffer_size", "first_instance")
        }
        self._instance_vbo = GL.glGenBuffers(1)
        # Drawn as decimated meshes within the depth bound: the cost of a batch grows with the faces drawn.
        self.meshes = [render_mesh(mesh, config.max_depth_error) for mesh in meshes]
        self._meshes = [self._upload_mesh(GL, mesh) for mesh in self.meshes]
        self._cull = [config.cull_back_faces and closed_outward(mesh) for mesh in self.meshes]
        self._fbo = GL.glGenFramebuffers(1)
        self._colour_rb, self._depth_rb = GL.glGenRenderbuffers(2)
        # One fixed tile layout: a particle's pixels then depend only on its place in the batch, never on the batch
        # size (the projection's rounding changes with the framebuffer size), so reruns are bit-identical.
        self._ensure_framebuffer(GL, self._max_columns * self._width, self._max_rows * self._height)

    @property
    def particles_per_pass(self) -> int:
        """Particles drawn per framebuffer pass (column-major grid of max_framebuffer // (W, H) tiles)."""
        return self._max_columns * self._max_rows

    def _upload_mesh(self, GL, mesh: trimesh.Trimesh) -> tuple[int, int, int, int]:
        """-> (vao, vertex vbo, index buffer, index count)."""
        vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
        indices = np.ascontiguousarray(mesh.faces, dtype=np.uint32).ravel()
        vao = GL.glGenVertexArrays(1)
        vbo, ebo = GL.glGenBuffers(2)
        GL.glBindVertexArray(vao)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, vbo)
        GL.glBufferData(GL.GL_ARRAY_BUFFER, vertices.nbytes, vertices, GL.GL_STATIC_DRAW)
        GL.glEnableVertexAttribArray(0)
        GL.glVertexAttribPointer(0, 3, GL.GL_FLOAT, GL.GL_FALSE, 12, None)
        GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, ebo)
        GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, indices.nbytes, indices, GL.GL_STATIC_DRAW)
        # Per-instance T_cam_obj columns; pointed into the instance buffer at each pass (offsets depend on B).
        for column in range(4):
            GL.glEnableVertexAttribArray(1 + column)
            GL.glVertexAttribDivisor(1 + column, 1)
        GL.glBindVertexArray(0)
        return vao, vbo, ebo, indices.size

    def _ensure_framebuffer(self, GL, width: int, height: int) -> None:
        """Grow the framebuffer (R32F linear depth + float z-buffer) to at least ``width`` x ``height`` px."""
        if width <= self._fb_size[0] and height <= self._fb_size[1]:
            return
        w, h = max(width, self._fb_size[0]), max(height, self._fb_size[1])
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._colour_rb)
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_R32F, w, h)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._depth_rb)
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT32F, w, h)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._fbo)
        GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, self._colour_rb)
        GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, self._depth_rb)
        status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
        if status != GL.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError(f"framebuffer {w}x{h} incomplete (status {status:#x})")
        self._fb_size = (w, h)

    def render(self, T_world_obj: np.ndarray, drawn: np.ndarray | None = None) -> np.ndarray:
        """Object poses in the table frame (B, K, 4, 4) -> camera-z depth (B, H, W) float32, 0 = no object.
        ``drawn`` (B, K) bool: which objects each scene draws (default all); an object left out is not drawn at
        all (its pose is ignored), which costs nothing, so scenes that share objects can draw them once
        (``render.shared``)."""
        T_world_obj = np.asarray(T_world_obj, dtype=np.float64)
        if T_world_obj.ndim != 4 or T_world_obj.shape[1:] != (self.n_objects, 4, 4):
            raise ValueError(f"poses must be (B, {self.n_objects}, 4, 4), got {T_world_obj.shape}")
        B = T_world_obj.shape[0]
        drawn = np.ones((B, self.n_objects), dtype=bool) if drawn is None else np.asarray(drawn, dtype=bool)
        if drawn.shape != (B, self.n_objects):
            raise ValueError(f"drawn must be ({B}, {self.n_objects}), got {drawn.shape}")
        out = np.empty((B, self._height, self._width), dtype=np.float32)
        if B == 0:
            return out
        from OpenGL import GL

        self._platform.make_current()
        # (K, B, 4, 4) column-major float32: the layout a mat4 attribute reads, one contiguous block per object.
        T_cam_obj = (self._T_cam_world @ T_world_obj).transpose(1, 0, 3, 2).astype(np.float32)
        per_pass = self.particles_per_pass
        for start in range(0, B, per_pass):
            stop = min(start + per_pass, B)
            self._render_pass(GL, np.ascontiguousarray(T_cam_obj[:, start:stop]), drawn[start:stop],
                              out[start:stop])
        return out

    def _render_pass(self, GL, T_cam_obj: np.ndarray, drawn: np.ndarray, out: np.ndarray) -> None:
        """One framebuffer pass. ``T_cam_obj``: (K, n, 4, 4) transposed float32; ``drawn``: (n, K) bool; ``out``:
        (n, H, W) contiguous, filled in place."""
        n = T_cam_obj.shape[1]
        rows = self._max_rows
        columns = math.ceil(n / rows)
        # Only the tiles in use are cleared and drawn: a small batch (settling's round trips) then costs little more
        # than its own tiles.
        used_w, used_h = columns * self._width, min(n, rows) * self._height
        self._ensure_framebuffer(GL, used_w, used_h)
        fb_w, fb_h = self._fb_size

        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._fbo)
        GL.glViewport(0, 0, fb_w, fb_h)
        GL.glEnable(GL.GL_SCISSOR_TEST)  # clear only the tiles in use
        GL.glScissor(0, 0, used_w, used_h)
        GL.glClearColor(0.0, 0.0, 0.0, 0.0)
        GL.glClearDepth(1.0)
        GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthFunc(GL.GL_LESS)
        for plane in range(4):
            GL.glEnable(GL.GL_CLIP_DISTANCE0 + plane)

        GL.glUseProgram(self._program)
        P = projection_matrix(self.camera.K, fb_w, fb_h)
        GL.glUniformMatrix4fv(self._uniforms["projection"], 1, GL.GL_TRUE, P)
        GL.glUniform2i(self._uniforms["tile_size"], self._width, self._height)
        GL.glUniform1i(self._uniforms["rows"], rows)
        GL.glUniform2f(self._uniforms["framebuffer_size"], fb_w, fb_h)

        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._instance_vbo)
        GL.glBufferData(GL.GL_ARRAY_BUFFER, T_cam_obj.nbytes, T_cam_obj, GL.GL_STREAM_DRAW)
        block = n * 64  # bytes of one object's matrices
        # The image is drawn with v along GL's window y, a mirror of GL's convention, so outward (counter-
        # clockwise) faces arrive clockwise.
        GL.glFrontFace(GL.GL_CW)
        GL.glCullFace(GL.GL_BACK)
        for k, (vao, _, _, count) in enumerate(self._meshes):
            (GL.glEnable if self._cull[k] else GL.glDisable)(GL.GL_CULL_FACE)
            GL.glBindVertexArray(vao)
            # One instanced draw per run of consecutive tiles that draw this object, its instances read from the
            # run's first tile on.
            for first, last in _runs(drawn[:, k]):
                for column in range(4):
                    offset = k * block + first * 64 + column * 16
                    _vertex_attrib_pointer(1 + column, 4, GL.GL_FLOAT, GL.GL_FALSE, 64, ctypes.c_void_p(offset))
                GL.glUniform1i(self._uniforms["first_instance"], first)
                GL.glDrawElementsInstanced(GL.GL_TRIANGLES, count, GL.GL_UNSIGNED_INT, None, last - first)
        GL.glBindVertexArray(0)
        GL.glDisable(GL.GL_CULL_FACE)

        GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 4)
        # A column of tiles is (count * H, W) contiguous rows: read each straight into its slots of `out`,
        # which saves a re-tiling copy as costly as the read itself.
        for column, first in enumerate(range(0, n, rows)):
            count = min(rows, n - first)
            GL.glReadPixels(
                column * self._width, 0, self._width, count * self._height, GL.GL_RED, GL.GL_FLOAT,
                out[first].ctypes.data,
            )
        GL.glDisable(GL.GL_SCISSOR_TEST)

    def close(self) -> None:
        """Free the GL objects and the context. Idempotent."""
        if self._platform is None:
            return
        from OpenGL import GL

        self._platform.make_current()
        for vao, vbo, ebo, _ in self._meshes:
            GL.glDeleteVertexArrays(1, [vao])
            GL.glDeleteBuffers(2, [vbo, ebo])
        GL.glDeleteFramebuffers(1, [self._fbo])
        GL.glDeleteRenderbuffers(2, [self._colour_rb, self._depth_rb])
        GL.glDeleteBuffers(1, [self._instance_vbo])
        GL.glDeleteProgram(self._program)
        self._platform.delete_context()
        self._platform = None

    def __enter__(self) -> "DepthRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def render_depth(
    camera: Camera, meshes: list[trimesh.Trimesh], T_world_obj: np.ndarray, config: RenderConfig = RenderConfig()
) -> np.ndarray:
    """One-off render of one scene: poses (K, 4, 4) in the table frame -> (H, W) float32 camera-z depth."""
    with DepthRenderer(camera, meshes, config) as renderer:
        return renderer.render(np.asarray(T_world_obj)[None])[0]
