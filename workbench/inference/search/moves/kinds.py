"""The default search's move kinds: each a ``context.Move`` over one proposal function of its module (``gaussian``,
``resting``, ``stacking``, ``datadriven``, ``refine``, ``relocate``), listed in ``moves.MOVES``."""

from __future__ import annotations

from workbench.inference.search import datadriven, refine
from workbench.inference.search.moves import gaussian, relocate, resting, stacking
from workbench.inference.search.moves.context import Move
from workbench.inference.search.moves.proposal import Proposal


class Joint(Move):
    """The paper's diffusion: every object takes a Gaussian step."""

    name, code, share = "joint", 2, 0.25

    def propose(self, rng, parents, ctx):
        return gaussian.propose_joint(rng, parents, ctx.sigma, ctx.scales, ctx.state)


class Single(Move):
    """One object takes a Gaussian step; the others stay."""

    name, code, share = "single", 3, 0.30

    def propose(self, rng, parents, ctx):
        return gaussian.propose_single(rng, parents, ctx.sigma, ctx.scales, ctx.state, ctx.choose)


class Face(Move):
    """One object onto another resting face."""

    name, code, share, tilts = "face", 4, 0.05, True

    def propose(self, rng, parents, ctx):
        return resting.propose_face(rng, parents, ctx.geometry.rest, ctx.geometry.hulls, ctx.choose)


class Turn(Move):
    """One object turned by 90, 180 or 270 degrees about the vertical."""

    name, code, share = "turn", 5, 0.06

    def propose(self, rng, parents, ctx):
        return resting.propose_turn(rng, parents, ctx.choose)


class Stack(Move):
    """One object onto another object, or off it."""

    name, code, share = "stack", 6, 0.04

    def propose(self, rng, parents, ctx):
        return stacking.propose_stack(rng, parents, ctx.geometry.hulls, ctx.choose)


class Data(Move):
    """One object to a data-driven candidate."""

    name, code, share, after_refit = "data", 7, 0.15, True

    def propose(self, rng, parents, ctx):
        return datadriven.propose_data(rng, parents, ctx.library, ctx.choose, ctx.geometry.radius)


class Icp(Move):
    """One object refined by ICP against the observed points near it (main-process work: proposed after the
    cheap kinds, while the workers project those)."""

    name, code, share, after_refit = "icp", 8, 0.10, True

    def propose(self, rng, parents, ctx):
        g = ctx.geometry
        return refine.propose_icp(rng, parents, g.points, g.samples, g.reach, ctx.choose, log_q=ctx.method == "mcpf")


class Relocate(Move):
    """Each object with probability 1/K to a random place (``random_relocations``); symmetric."""

    name, code, share = "relocate", 9, 0.05

    def propose(self, rng, parents, ctx):
        problem = ctx.problem
        return Proposal.symmetric(relocate.random_relocations(rng, parents, 1.0 / problem.n_objects, problem.models,
                                                     problem.table))
