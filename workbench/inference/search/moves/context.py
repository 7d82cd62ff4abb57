"""What a move kind of the default search is (``Move``) and what it works with: per-object geometry computed once
per problem (``SearchGeometry``), and one iteration's view of the search (``MoveContext``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import trimesh

from workbench.inference.answer import assemble
from workbench.inference.search.datadriven import Library
from workbench.inference.search.moves import resting
from workbench.inference.search.moves.proposal import Proposal
from workbench.inference.search.scenepoints import ModelSamples, ScenePoints, model_samples, observed_points
from workbench.inference.smc.particles import Sigma
from workbench.meshes.heavy import HEAVY_FACES, working_mesh
from workbench.problem.problem import Problem
from workbench.problem.scene import ObjectModel


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
    solids: list[assemble.Solid]

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
            solids=[assemble.solid(h, s) for h, s in zip(hulls, samples)],
        )


def search_mesh(model: ObjectModel, problem: Problem) -> trimesh.Trimesh:
    """The mesh the search's geometry is computed from: the model's own; for one of more than
    ``meshes.heavy.HEAVY_FACES`` faces, the render mesh (decimated within the renderer's depth error, chosen once and
    cached on disk by the evaluators), so that a 1.3M-face model costs no minutes here, in every run."""
    if len(model.mesh.faces) <= HEAVY_FACES:
        return model.mesh
    from workbench.render.depth import render_mesh  # only here: importing it picks the OpenGL platform

    mesh = render_mesh(model.mesh, problem.config.render.max_depth_error)
    return mesh if len(mesh.faces) <= HEAVY_FACES else working_mesh(model.mesh)


@dataclass(frozen=True)
class MoveContext:
    """What a ``Move`` may use in one iteration. ``choose`` (K,): how often each object is the one moved
    (the objects that explain their part of the observation worst most often); ``scales`` (K,): the Gaussian
    steps' scale per object (coarse to fine)."""

    problem: Problem
    geometry: SearchGeometry
    library: Library | None
    sigma: Sigma
    state: str  # "6dof" or "xyzyaw"
    method: str  # "pipf" or "mcpf"
    choose: np.ndarray
    scales: np.ndarray


class Move:
    """One move kind of the default search: drawn per particle and iteration from ``moves.MoveMix``, it proposes
    a scene from each parent with its log-q correction. A new kind is a module with a subclass and one line in
    ``moves.MOVES``; its share of the mix and its per-kind counts follow from there. The built-in kinds are in
    ``kinds``."""

    name: ClassVar[str]  # the mix's key and the kind's label, e.g. "joint"
    # The MoveKind value stored with each particle it produces (sessions keep it): unique, never renumbered.
    code: ClassVar[int]
    share: ClassVar[float]  # its default share of the mix (the shares are normalised when drawn)
    # Changes roll or pitch: not drawn in the paper's reduced state (x, y, z, yaw).
    tilts: ClassVar[bool] = False
    # Uses the candidates refitted this iteration: proposed after the refit, while the workers already project
    # the other kinds' hypotheses.
    after_refit: ClassVar[bool] = False

    def propose(self, rng: np.random.Generator, parents: np.ndarray, ctx: MoveContext) -> Proposal:
        """Parents (B, K, 4, 4), table frame -> their proposals."""
        raise NotImplementedError
