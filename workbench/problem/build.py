"""From files to a ready estimation problem, and from an estimate back to BOP results: the glue the CLI, the
benchmark and the app share."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from workbench.inference.answer.posterior import Posterior
from workbench.io import bop
from workbench.io.bop import ResultRow
from workbench.problem.problem import Problem, ProblemConfig, build_problem
from workbench.problem.scene import Frame, ObjectModel
from workbench.problem.support import estimate_support


def problem_for_frame(frame: Frame, models: dict[int, ObjectModel], config: ProblemConfig = ProblemConfig()) -> Problem:
    """Find the table (or the raised support the objects stand on) in the frame and assemble the problem for the
    objects the frame lists (in that order)."""
    listed = [models[i] for i in frame.object_ids]
    camera, table = estimate_support(frame, objects_volume=sum(m.mass / m.density for m in listed),
                                     objects_reach=sum(float(m.mesh.extents.max()) for m in listed))
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


def result_rows(frame: Frame, problem: Problem, best: np.ndarray, scores: np.ndarray, seconds: float
                ) -> list[ResultRow]:
    """The best scene (K, 4, 4) in the table frame -> one BOP result row per object (camera frame)."""
    T_cam_obj = problem.camera.T_cam_world[None] @ best
    return [
        ResultRow(frame.scene_id, frame.im_id, m.obj_id, float(s), T, seconds)
        for m, s, T in zip(problem.models, scores, T_cam_obj)
    ]


@dataclass
class ModeRow(ResultRow):
    """A result row that is one mode of an object's posterior (``score`` its probability). The object's first row
    also carries the whole posterior of the object as ``posterior_record`` writes it (JSON-able), else None;
    ``posterior_seconds``: what the frame's posterior sweep took of its ``time``."""

    posterior: dict | None = None
    posterior_seconds: float = 0.0


def posterior_rows(frame: Frame, problem: Problem, posterior: Posterior, seconds: float) -> list[ModeRow]:
    """Each object's modes as BOP result rows, best first, ``score`` = the mode's probability (camera frame): a
    reader that takes each object's top row gets the estimate."""
    rows = []
    for o, record in zip(posterior.objects, posterior_record(problem, posterior)):
        for i, mode in enumerate(o.modes):
            rows.append(ModeRow(frame.scene_id, frame.im_id, problem.models[o.obj].obj_id, mode.probability,
                                problem.camera.T_cam_world @ mode.T, seconds, record if i == 0 else None,
                                posterior.seconds))
    return rows


def posterior_record(problem: Problem, posterior: Posterior) -> list[dict]:
    """Per object, its posterior in BOP's units and frame: each mode's pose in the camera frame (``R`` row-major,
    ``t`` mm), probability, log-likelihood and gap to the estimate (log-units) and what it is; the spread of its
    position (mm); the range of headings about the table's vertical (``vertical_cam``, a unit vector in the camera
    frame) that the view leaves open (degrees about the estimate's, or null); the share of its estimate's surface
    the sensor sees through, and the chance that it is none of the modes (``elsewhere``, beside the modes, whose
    probabilities sum to 1)."""
    T_cam_world = problem.camera.T_cam_world
    out = []
    for o in posterior.objects:
        model = problem.models[o.obj]
        modes = []
        for m in o.modes:
            T = T_cam_world @ m.T
            modes.append({"R": [round(float(v), 12) for v in T[:3, :3].ravel()],
                          "t": [round(1000.0 * float(v), 9) for v in T[:3, 3]],
                          "probability": round(m.probability, 6), "loglik": round(m.loglik, 3),
                          "gap": round(m.gap, 3), "what": m.what})
        out.append({"obj_id": model.obj_id, "name": model.name, "modes": modes,
                    "position_spread_mm": round(1000.0 * o.position_spread_m, 3),
                    "yaw_range_deg": None if o.yaw_range_deg is None else list(o.yaw_range_deg),
                    "seen_through": round(o.seen_through, 4), "elsewhere": round(o.elsewhere, 6),
                    "vertical_cam": [round(float(v), 12) for v in T_cam_world[:3, 2]],
                    "temperature": posterior.temperature})
    return out
