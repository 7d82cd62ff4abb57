"""A toy problem and a fast evaluator for the fast tier: the filter core and the moves without pybullet or OpenGL.

``ToyEvaluator`` implements ``evaluation.Evaluator`` with no physics and no rendering: "projection" drops each object
straight down until its lowest vertex touches the table (or the sink below it), and the log-likelihood is made up: a
Gaussian in each object's distance to a target scene and its rotation angle from the target's (up to the model's
symmetries). numpy only, so runs are exact and seeded.
"""

from __future__ import annotations

import numpy as np
import trimesh

from workbench.evaluation import Done, Evaluation, admissible, run_here
from workbench.geometry import make_pose, rot_z, rotation_angle
from workbench.physics import STATUS_AS_GIVEN, STATUS_OUTSIDE, STATUS_REST
from workbench.problem.problem import Problem, ProblemConfig
from workbench.problem.scene import Camera, ObjectModel, Table


def toy_problem(sizes=((0.10, 0.06, 0.04), (0.05, 0.05, 0.12))) -> Problem:
    """Boxes of ``sizes`` (m) on a 1 x 1 m table whose object region is +-15 cm, seen from 70 cm above. The
    observation is empty: the toy evaluator never looks at it."""
    models = [ObjectModel(i + 1, trimesh.creation.box(extents=s)) for i, s in enumerate(sizes)]
    K = np.array([[300.0, 0, 80], [0, 300.0, 60], [0, 0, 1]])
    T_cam_world = make_pose(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.7])  # looking straight down
    camera = Camera(K, 160, 120, T_cam_world)
    blank = np.zeros((120, 160), np.float32)
    return Problem(camera, Table(-0.5, 0.5, -0.5, 0.5), models, (0, 0, 160, 120), camera, blank, blank,
                   ProblemConfig())


def toy_target(problem: Problem) -> np.ndarray:
    """A scene (K, 4, 4) of the toy problem's objects resting apart on the table, table frame."""
    out = []
    for k, model in enumerate(problem.models):
        T = make_pose(rot_z(0.4 + k), [0.08 * (2 * k - 1), 0.03, 0.0])
        out.append(drop(T[None], model.mesh.vertices, 0.0)[0])
    return np.stack(out)


def drop(T: np.ndarray, vertices: np.ndarray, sink: float | np.ndarray) -> np.ndarray:
    """Poses (B, 4, 4) moved along z until the lowest of ``vertices`` (V, 3) is at -``sink`` (m)."""
    out = T.copy()
    low = np.min(np.einsum("bij,vj->bvi", T[:, :3, :3], vertices)[..., 2], axis=1)  # (B,)
    out[:, 2, 3] = -np.asarray(sink) - low
    return out


class ToyEvaluator:
    """``Evaluator`` over a toy problem: hypotheses dropped onto the table, scored against ``target`` (K, 4, 4) by
    -(d / sigma_m)^2 / 2 - (angle / sigma_rad)^2 / 2 summed over objects. Counts the hypotheses it evaluated."""

    def __init__(self, problem: Problem, target: np.ndarray, sigma_m: float = 0.01, sigma_rad: float = 0.3):
        self.problem, self.target = problem, np.asarray(target, dtype=np.float64)
        self.sigma_m, self.sigma_rad = sigma_m, sigma_rad
        self.evaluated = 0

    def evaluate(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Evaluation:
        hypotheses = np.asarray(hypotheses, dtype=np.float64)
        B, K = hypotheses.shape[:2]
        sink = np.zeros(B) if sink is None else np.asarray(sink, dtype=np.float64)
        self.evaluated += B
        if project:
            projected = np.stack([drop(hypotheses[:, k], m.mesh.vertices, sink)
                                  for k, m in enumerate(self.problem.models)], axis=1)
            status = np.full(B, STATUS_REST, np.int8)
        else:
            projected, status = hypotheses.copy(), np.full(B, STATUS_AS_GIVEN, np.int8)
        loglik = np.zeros(B)
        for k, model in enumerate(self.problem.models):
            d = np.linalg.norm(projected[:, k, :3, 3] - self.target[k, :3, 3], axis=-1)
            rel = np.swapaxes(projected[:, k, :3, :3], -1, -2) @ self.target[k, :3, :3]  # (B, 3, 3)
            angle = rotation_angle(rel[:, None] @ model.symmetries[None, :, :3, :3]).min(axis=1)
            loglik -= 0.5 * (d / self.sigma_m) ** 2 + 0.5 * (angle / self.sigma_rad) ** 2
        outside = ~admissible(projected, self.problem)
        status[outside], loglik[outside] = STATUS_OUTSIDE, -np.inf
        return Evaluation(projected, loglik, status, np.zeros(B))

    def submit(self, hypotheses: np.ndarray, sink: np.ndarray | None = None, project: bool = True) -> Done:
        return Done(self.evaluate(hypotheses, sink, project))

    def map(self, fn, calls: list[tuple]) -> list:
        return run_here(self.problem)(fn, calls)

    def close(self) -> None:
        pass
