"""The default search's geometry of each object, computed once per problem from its mesh (``SearchGeometry``):
resting poses, surface samples, convex hulls and their reach, the solids of the assemblies' overlap test, and the
observed points above the table. Every search helper takes it as one argument."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from workbench.inference.search.moves import resting
from workbench.inference.search.scenepoints import (
    ModelSamples,
    ScenePoints,
    model_samples,
    observed_points,
)
from workbench.meshes.heavy import HEAVY_FACES, working_mesh
from workbench.problem.problem import Problem
from workbench.problem.scene import ObjectModel

HULL_POINTS = 64  # vertices of the simplified hull used for the assemblies' inside test
TEST_POINTS = 200  # core points per object tested against the others' hulls
CORE = 0.7  # the core: the surface samples pulled this far towards the centroid (surface points of two objects
# at one place lie on each other's surface, not inside it; touching objects' cores stay apart)


@dataclass(frozen=True)
class Solid:
    """An object's shape for the inside test, object frame: ``planes`` (F, 4) of a simplified convex hull, unit
    outward normal and offset (inside where ``n . x + d <= 0``); ``points`` (M, 3) its core (see CORE), metres;
    ``radius`` (m) of a sphere about the origin holding both."""

    planes: np.ndarray
    points: np.ndarray
    radius: float


def solid(hull_vertices: np.ndarray, samples: ModelSamples) -> Solid:
    """The Solid of an object from its convex hull's vertices (V, 3) and its surface samples. The hull is reduced
    to HULL_POINTS vertices by farthest-point sampling, so it lies within the full hull (the test errs towards
    'touching')."""
    v = np.asarray(hull_vertices, dtype=np.float64)
    chosen = [int(np.argmax(np.linalg.norm(v - v.mean(axis=0), axis=1)))]
    d = np.linalg.norm(v - v[chosen[0]], axis=1)
    while len(chosen) < min(HULL_POINTS, len(v)):
        chosen.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(v - v[chosen[-1]], axis=1))
    step = max(1, len(samples.points) // TEST_POINTS)
    surface = samples.points[::step][:TEST_POINTS]
    centre = surface.mean(axis=0)
    core = centre + CORE * (surface - centre)
    radius = float(max(np.linalg.norm(v, axis=1).max(), np.linalg.norm(core, axis=1).max()))
    return Solid(ConvexHull(v[chosen]).equations, core, radius)



@dataclass
class SearchGeometry:
    """Per object (K of them): ``rest`` its resting poses, ``samples`` surface samples, ``hulls`` convex-hull
    vertices (V, 3) object frame, ``reach`` (K,) m horizontal distance from the origin to the farthest hull vertex,
    ``radius`` (K,) m the same in 3D, ``solids`` for the assemblies' overlap test; ``points`` the observed points
    above the table."""

    rest: list[resting.RestingPoses]
    samples: list[ModelSamples]
    hulls: list[np.ndarray]
    reach: np.ndarray
    radius: np.ndarray
    points: ScenePoints
    solids: list[Solid]

    @classmethod
    def of(cls, problem: Problem, upright: bool) -> "SearchGeometry":
        """Computed from the problem's meshes and observation; ``upright``: the reduced state's resting poses
        only (no object laid on its side)."""
        meshes = [search_mesh(m, problem) for m in problem.models]
        hulls = [np.asarray(resting.reduced_hull(m).vertices, dtype=np.float64) for m in meshes]
        samples = [model_samples(m) for m in meshes]
        return cls(
            rest=[resting.resting_poses(m, upright_only=upright) for m in meshes],
            samples=samples,
            hulls=hulls,
            reach=np.array([float(np.max(np.linalg.norm(h[:, :2], axis=1))) for h in hulls]),
            radius=np.array([float(np.max(np.linalg.norm(h, axis=1))) for h in hulls]),
            points=observed_points(problem),
            solids=[solid(h, s) for h, s in zip(hulls, samples)],
        )


def search_mesh(model: ObjectModel, problem: Problem) -> trimesh.Trimesh:
    """The mesh the search's geometry is computed from: the model's own; for one of more than
    ``meshes.heavy.HEAVY_FACES`` faces, the render mesh (decimated within the renderer's depth error, chosen once and
    cached on disk by the evaluators), so that a 1.3M-face model costs no minutes here, in every run."""
    if len(model.mesh.faces) <= HEAVY_FACES:
        return model.mesh
    from workbench.render.depth import (
        render_mesh,  # only here: importing it picks the OpenGL platform
    )

    mesh = render_mesh(model.mesh, problem.config.render.max_depth_error)
    return mesh if len(mesh.faces) <= HEAVY_FACES else working_mesh(model.mesh)
