"""From files to a ready estimation problem, and from an estimate back to BOP results: the glue the CLI, the
benchmark and the app share."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from workbench.io import bop
from workbench.io.bop import ResultRow
from workbench.problem import Problem, ProblemConfig, build_problem
from workbench.scene import Frame, ObjectModel
from workbench.support import estimate_support


def problem_for_frame(frame: Frame, models: dict[int, ObjectModel], config: ProblemConfig = ProblemConfig()) -> Problem:
    """Find the table in the frame and assemble the problem for the objects the frame lists (in that order)."""
    camera, table = estimate_support(frame)
    return build_problem(frame, [models[i] for i in frame.object_ids], camera, table, config)


def load_bop_problem(
    dataset: Path,
    scene_id: int,
    im_id: int,
    split: str | None = None,
    object_ids: list[int] | None = None,
    config: ProblemConfig = ProblemConfig(),
    density: float = 1000.0,
    friction: float = 0.75,
) -> tuple[Frame, Problem]:
    frame = bop.load_frame(dataset, scene_id, im_id, split=split, object_ids=object_ids)
    models = bop.load_models(dataset, sorted(set(frame.object_ids)), density=density, friction=friction)
    return frame, problem_for_frame(frame, models, config)


def result_rows(frame: Frame, problem: Problem, best: np.ndarray, scores: np.ndarray, seconds: float) -> list[ResultRow]:
    """The best scene (K, 4, 4) in the table frame -> one BOP result row per object (camera frame)."""
    T_cam_obj = problem.camera.T_cam_world[None] @ best
    return [
        ResultRow(frame.scene_id, frame.im_id, m.obj_id, float(s), T, seconds)
        for m, s, T in zip(problem.models, scores, T_cam_obj)
    ]
