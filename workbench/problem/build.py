"""From files to a ready estimation problem: the glue the CLI, the benchmark and the app share (an estimate's way
back to BOP results is ``io/results.py``)."""

from __future__ import annotations

from pathlib import Path

from workbench.io import bop
from workbench.problem.problem import Problem, ProblemConfig, build_problem
from workbench.problem.scene import Frame, ObjectModel
from workbench.problem.support import estimate_support


def problem_for_frame(frame: Frame, models: dict[int, ObjectModel], config: ProblemConfig = ProblemConfig(),
                      raised: bool = True) -> Problem:
    """Find the table (or the raised support the objects stand on) in the frame and assemble the problem for the
    objects the frame lists (in that order). ``raised`` False: the frame's given table pose is the support
    (``estimate_support``)."""
    listed = [models[i] for i in frame.object_ids]
    camera, table = estimate_support(frame, objects_volume=sum(m.mass / m.density for m in listed),
                                     objects_reach=sum(float(m.mesh.extents.max()) for m in listed), raised=raised)
    return build_problem(frame, listed, camera, table, config)


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
