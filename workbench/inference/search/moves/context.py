"""What a move kind of the default search is (``Move``) and what it works with: one iteration's view of the search
(``MoveContext``), with the per-object geometry computed once per problem (``geometry.SearchGeometry``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from workbench.inference.search.datadriven import Library
from workbench.inference.search.geometry import SearchGeometry
from workbench.inference.search.moves.proposal import Proposal
from workbench.inference.smc.particles import Sigma
from workbench.problem.problem import Problem


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
