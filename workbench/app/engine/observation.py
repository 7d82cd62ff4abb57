"""The static picture of a loaded frame, built in the engine process and sent to the server once per load:
the depth frame as a coloured point cloud, the depth image for the panel, the table, the meshes, the camera and
the problem grid onto which heatmaps are drawn."""

from __future__ import annotations

import numpy as np

from workbench.app.protocol import MeshData, ObservationView, PointSet
from workbench.app.ui.widgets.colors import apply_map, robust_range
from workbench.geometry import invert_pose, transform_points
from workbench.meshes.heavy import HEAVY_FACES
from workbench.problem.problem import Problem
from workbench.problem.scene import Camera, Frame, display_names

# Software WebGL pays for every pixel a point covers. Near the objects the cloud keeps enough points to read their
# shape; the rest of the table and the background only give context, drawn four times coarser per axis.
NEAR_POINTS = 10_000
FAR_STRIDE = 4  # times the near stride
NEAR_MARGIN = 0.05  # m around the object region still drawn finely
# A point's diameter over the spacing of its pixels at its depth. Below 1, so that the estimate drawn on the same
# surface shows between the points instead of hiding under them (0.9 buried the converged demo's estimate).
POINT_FILL = 0.6
# The coarse points' diameter over their spacing: dots, not a closed surface. Squares as wide as their spacing
# covered most of the view (~50-90 ms of every software-rendered frame); half as wide cover a quarter of that.
FAR_FILL = 0.5
MAX_IMAGE_WIDTH = 320  # the panel is ~20 em wide
# Observed points are grey: no object, particle, label or truth colour is a grey, so whatever is drawn on the points
# stands out from them. Dark (low) to pale (high) above the table; the table's own points a warm mid grey.
GREYS = np.array([[70, 74, 82], [228, 228, 232]], dtype=np.float64)
TABLE_POINTS = (160, 152, 140)
BELOW_POINTS = (60, 60, 60)
OUTLINE_FACES = 300  # the coarse mesh whose feature edges outline an object (ground truth, labels, particles)
OUTLINE_DEGREES = 20.0  # a coarse mesh's edge is drawn where its faces meet at more than this
# The particles' outline, drawn for up to hundreds of particles per object: the feature edges of a far coarser
# decimation (a YCB frame's 32 particles drawn with the truth's outline cost 4x the demo's per frame in software WebGL).
CLOUD_OUTLINE_FACES = 40
CLOUD_OUTLINE_DEGREES = 35.0
SOLID_FACES = 2000  # a solid drawn object: YCB-Video's scans have 15,728 faces, four of them cost more than the demo
CLOUD_MAX_EDGES = 64  # more (an open scan keeps every hole's rim: YCB's master chef can 1,091): its box instead


def backproject(camera: Camera, depth: np.ndarray, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Pixels with a reading -> (points (P, 3) in the camera frame, flat pixel indices (P,) into depth[::s, ::s]).

    Pixel (u, v) is the ray through image point (u, v) of K, as in the renderer."""
    d = depth[::stride, ::stride]
    v, u = np.nonzero(d > 0)
    z = d[v, u].astype(np.float64)
    K = camera.K
    x = (u * stride - K[0, 2]) / K[0, 0] * z
    y = (v * stride - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=-1), v * d.shape[1] + u


def height_top(z: np.ndarray) -> float:
    """The height (m) coloured yellow: the 99th percentile of the points above the table, at least 5 cm."""
    return max(0.05, float(np.percentile(z[z > 0.005], 99))) if np.any(z > 0.005) else 0.05


def height_colors(z: np.ndarray, top: float | None = None) -> tuple[np.ndarray, str]:
    """Grey by height above the table: the table itself warm grey, objects from dark grey (low) to pale (at
    ``top``, default the 99th percentile of ``z`` above the table, at least 5 cm), points below the table darker
    -> ((P, 3) uint8, what the colours mean)."""
    top = height_top(z) if top is None else top
    colors = apply_map(z, 0.0, top, GREYS)
    colors[np.abs(z) <= 0.005] = TABLE_POINTS
    colors[z < -0.005] = BELOW_POINTS
    return colors, f"grey by height above the table, 0 (dark) to {top * 100:.0f} cm (pale); table warm grey"


def grey_of(rgb: np.ndarray) -> np.ndarray:
    """(P, 3) uint8 colours -> their luminance as (P, 3) uint8 greys, kept within GREYS' range."""
    y = rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    y = GREYS[0, 0] + (GREYS[1, 0] - GREYS[0, 0]) * y / 255.0
    return np.repeat(np.round(y).astype(np.uint8)[:, None], 3, axis=1)


def outline_edges(vertices: np.ndarray, faces: np.ndarray, n_faces: int = OUTLINE_FACES,
                  degrees: float = OUTLINE_DEGREES) -> np.ndarray:
    """The lines that outline a mesh: its feature edges (faces meeting at more than ``degrees``) and open
    boundaries, on a quadric decimation to about ``n_faces`` faces -> (E, 2, 3) float32 segments, object frame.

    Every triangle edge of a 16k-face YCB scan was noise in the view and costly to draw in software WebGL;
    a box keeps its 12 edges, a can its rims and a few rings, a banana a coarse cage."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=True)
    if len(mesh.faces) > n_faces:
        try:
            import open3d as o3d

            source = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                               o3d.utility.Vector3iVector(mesh.faces.astype(np.int32)))
            simple = source.simplify_quadric_decimation(target_number_of_triangles=n_faces)
            if len(simple.triangles) > 2 * n_faces:
                # Stalled (YCB's master chef can stops at 1,174 faces, whose creases drew 1,299 edges: a third of
                # a real frame's drawing): near-coincident vertices block the collapses; merged, it decimates.
                merge = 0.01 * float(np.max(mesh.extents))
                source = (source.merge_close_vertices(merge).remove_degenerate_triangles()
                          .remove_duplicated_triangles().remove_non_manifold_edges())
                simple = source.simplify_quadric_decimation(target_number_of_triangles=n_faces)
            coarse = trimesh.Trimesh(np.asarray(simple.vertices), np.asarray(simple.triangles), process=True)
            if len(coarse.faces):
                mesh = coarse
        except ImportError:  # without open3d the full mesh's feature edges, fewer on smooth shapes
            pass
    sharp = mesh.face_adjacency_edges[mesh.face_adjacency_angles > np.radians(degrees)]
    edges, counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
    lines = np.concatenate([sharp, edges[counts == 1]]).reshape(-1, 2)
    if len(lines) == 0:  # a mesh smooth everywhere: its decimation's edges then
        lines = edges
    return np.asarray(mesh.vertices, np.float32)[lines]


def solid_mesh(mesh) -> tuple[np.ndarray, np.ndarray] | None:
    """``mesh`` (trimesh, metres) decimated for drawing as a solid, to about ``SOLID_FACES`` faces -> (vertices
    float32, faces int32), or None where it has no more than that (it is drawn as it is)."""
    if len(mesh.faces) <= SOLID_FACES:
        return None
    try:
        import open3d as o3d
    except ImportError:
        return None
    source = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices, np.float64)),
                                       o3d.utility.Vector3iVector(np.asarray(mesh.faces, np.int32)))
    simple = source.simplify_quadric_decimation(target_number_of_triangles=SOLID_FACES)
    if len(simple.triangles) == 0:
        return None
    return np.asarray(simple.vertices, np.float32), np.asarray(simple.triangles, np.int32)


def cloud_outline(mesh) -> np.ndarray:
    """The particles' outline of ``mesh`` (trimesh, metres): the feature edges of a decimation to about
    ``CLOUD_OUTLINE_FACES`` faces, or, where that still has over ``CLOUD_MAX_EDGES`` edges, the 12 edges of its
    oriented bounding box -> (E, 2, 3) float32, object frame."""
    edges = outline_edges(mesh.vertices, mesh.faces, CLOUD_OUTLINE_FACES, CLOUD_OUTLINE_DEGREES)
    if len(edges) <= CLOUD_MAX_EDGES:
        return edges
    box = mesh.bounding_box_oriented.to_mesh()
    creases = box.face_adjacency_edges[box.face_adjacency_angles > np.radians(45.0)]  # not the faces' diagonals
    return np.asarray(box.vertices)[creases].astype(np.float32)


def object_meshes(problem: Problem) -> list[MeshData]:
    """Each object as drawn: its mesh, with its outlines and solid decimated from it; those of a model of over
    ``meshes.heavy.HEAVY_FACES`` faces from its render mesh (a few thousand faces, made once and cached on disk by
    ``evaluation.local.prepare_meshes``, which says so while it works), not from the model itself: three
    decimations of a 1.3M-face sphere took 77 s here, in silence."""
    heavy = [len(m.mesh.faces) > HEAVY_FACES for m in problem.models]
    if any(heavy):
        from workbench.evaluation.local import prepare_meshes
        from workbench.inference.search.geometry import search_mesh

        prepare_meshes(problem)
    out = []
    for name, m, is_heavy in zip(display_names(problem.models), problem.models, heavy):
        drawn = search_mesh(m, problem) if is_heavy else m.mesh
        solid = solid_mesh(drawn)
        if is_heavy and solid is None:  # the render mesh is the solid (never the model's million faces)
            solid = np.asarray(drawn.vertices, np.float32), np.asarray(drawn.faces, np.int32)
        out.append(MeshData(name, np.asarray(m.mesh.vertices, np.float32), np.asarray(m.mesh.faces, np.int32),
                            outline_edges(drawn.vertices, drawn.faces), cloud_outline(drawn), solid))
    return out


def image_thumbnail(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) -> (H', W', 3) uint8 no wider than MAX_IMAGE_WIDTH."""
    stride = max(1, int(np.ceil(rgb.shape[1] / MAX_IMAGE_WIDTH)))
    return np.ascontiguousarray(rgb[::stride, ::stride, :3]).astype(np.uint8)


def depth_image(depth: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
    """(H, W) metres -> a coloured (H', W', 3) uint8 image no wider than MAX_IMAGE_WIDTH, and its depth range."""
    stride = max(1, int(np.ceil(depth.shape[1] / MAX_IMAGE_WIDTH)))
    d = depth[::stride, ::stride].astype(np.float64)
    lo, hi = robust_range(d[d > 0], 1.0, 99.0)
    return apply_map(np.where(d > 0, d, np.nan), lo, hi), (lo, hi)


def point_size(camera: Camera, depth: np.ndarray, stride: int, fill: float = POINT_FILL) -> float:
    """Diameter (m) of a point ``fill`` times as wide as the spacing of its pixel block of ``stride`` at the median
    depth: the data's spacing."""
    z = float(np.median(depth[depth > 0])) if np.any(depth > 0) else 1.0
    return fill * stride * z / float(camera.K[0, 0])


def split_near(points: np.ndarray, region: tuple[float, float, float, float], margin: float) -> np.ndarray:
    """(P, 3) table-frame points -> (P,) bool: within ``margin`` of the object region (x0, x1, y0, y1)."""
    x0, x1, y0, y1 = region
    return ((points[:, 0] >= x0 - margin) & (points[:, 0] <= x1 + margin)
            & (points[:, 1] >= y0 - margin) & (points[:, 1] <= y1 + margin))


def cloud_points(frame: Frame, camera: Camera, T_world_cam: np.ndarray, stride: int,
                 keep) -> tuple[np.ndarray, np.ndarray]:
    """The frame's pixels at ``stride`` where ``keep(points)`` holds -> (table-frame points (P, 3), flat pixel
    indices (P,) into depth[::stride, ::stride])."""
    p_cam, flat = backproject(camera, frame.depth, stride)
    points = transform_points(T_world_cam, p_cam)
    mask = keep(points)
    return points[mask], flat[mask]


def build_view(frame: Frame, problem: Problem, title: str, dataset=None, meshes: list[MeshData] | None = None
               ) -> ObservationView:
    """The frame as the workbench shows it; ``dataset``: its folder, for the Data tab. ``meshes``: the objects as
    another view of the same models drew them (the frame before in a sequence): their outlines and decimations are
    not made again (about a second for YCB-Video's four scans)."""
    camera = problem.camera
    T_world_cam = invert_pose(camera.T_cam_world)
    t = problem.table
    region = (t.region_min[0], t.region_max[0], t.region_min[1], t.region_max[1])
    # The near stride from a first count at full resolution; the far one a fixed multiple of it.
    p_all, _ = backproject(camera, frame.depth, 1)
    n_near = int(np.count_nonzero(split_near(transform_points(T_world_cam, p_all), region, NEAR_MARGIN)))
    stride = max(1, int(np.ceil(np.sqrt(n_near / NEAR_POINTS))))
    near_pts, near_flat = cloud_points(frame, camera, T_world_cam, stride,
                                       lambda pts: split_near(pts, region, NEAR_MARGIN))
    # The far stride is a multiple of the near one, so both sample the same pixel lattice.
    far_stride = stride * FAR_STRIDE
    far_pts, far_flat = cloud_points(frame, camera, T_world_cam, far_stride,
                                     lambda pts: ~split_near(pts, region, NEAR_MARGIN))
    if frame.rgb is not None:
        # The image's brightness, in grey: its texture without the hues the objects wear (the colours are in the
        # panel's thumbnail).
        near_rgb = grey_of(frame.rgb[::stride, ::stride, :3].reshape(-1, 3)[near_flat])
        far_rgb = grey_of(frame.rgb[::far_stride, ::far_stride, :3].reshape(-1, 3)[far_flat])
        legend = "the colour image's brightness, in grey (the image: Data tab)"
    else:
        top = height_top(near_pts[:, 2])  # the objects are near: they set the scale of both
        near_rgb, legend = height_colors(near_pts[:, 2], top)
        far_rgb, _ = height_colors(far_pts[:, 2], top)
    near = PointSet(near_pts.astype(np.float32), near_rgb, point_size(camera, frame.depth, stride))
    far = PointSet(far_pts.astype(np.float32), far_rgb, point_size(camera, frame.depth, far_stride, FAR_FILL))

    grid_cam, _ = backproject(problem.render_camera, problem.observed)
    grid_points = transform_points(T_world_cam, grid_cam)
    image, drange = depth_image(frame.depth)

    gt = None
    if frame.gt_T_cam_obj is not None:
        gt = T_world_cam[None] @ frame.gt_T_cam_obj
    return ObservationView(
        title=title,
        near=near,
        far=far,
        color_legend=legend,
        depth_image=image,
        depth_range=drange,
        table=(t.x_min, t.x_max, t.y_min, t.y_max),
        region=region,
        meshes=meshes if meshes is not None else object_meshes(problem),
        T_world_cam=T_world_cam,
        K=np.asarray(camera.K, np.float64),
        image_size=(camera.width, camera.height),
        grid_points=grid_points.astype(np.float32),
        grid_point_size=point_size(problem.render_camera, problem.observed, 1),
        grid_mask=problem.observed > 0,
        gt_T_world_obj=gt,
        rgb_image=None if frame.rgb is None else image_thumbnail(frame.rgb),
        where=None if dataset is None else (str(dataset), int(frame.scene_id), int(frame.im_id)),
    )
