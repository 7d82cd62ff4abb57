"""The estimator's settled answer as plain JSON, for sessions, and back: the settled scene, its log-likelihood, its
near ties and the posterior per object (``inference.answer.posterior``), in the table frame and in metres, float64 exact
(Python's JSON writes the shortest repr that reads back to the same double). A loaded session shows the same modes
and confidences as the saved run without settling again.

``parse_answer`` checks every value and raises ValueError naming the entry at fault ("answer.posterior.objects[1]
.modes[0].probability ..."): ``sessions`` turns that into an InputError naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.errors import InputError
from workbench.geometry import check_rigid
from workbench.inference.answer.posterior import Mode, ObjectPosterior, Posterior
from workbench.inference.answer.settle import Tie


@dataclass(frozen=True)
class Answer:
    """What ``Estimator.settle`` found for one estimate: ``scene`` (K, 4, 4) table frame, ``loglik`` as given,
    ``ties`` and ``posterior`` (None for the paper's search)."""

    scene: np.ndarray
    loglik: float
    ties: list[Tie]
    posterior: Posterior | None


def answer_json(answer: Answer) -> dict:
    """``answer`` as plain JSON lists, numbers and strings."""
    return {
        "scene": np.asarray(answer.scene, dtype=np.float64).tolist(),
        "loglik": float(answer.loglik),
        "ties": [{"obj": int(t.obj), "turn": t.turn, "T": np.asarray(t.T, np.float64).tolist(), "gap": float(t.gap)}
                 for t in answer.ties],
        "posterior": None if answer.posterior is None else posterior_json(answer.posterior),
    }


def posterior_json(posterior: Posterior) -> dict:
    """A posterior as plain JSON: per object its modes (pose, log-likelihood, gap, probability, what), position
    spread (m) and open heading range (degrees, or null), and the temperature."""
    return {
        "temperature": float(posterior.temperature),
        "objects": [{
            "obj": int(o.obj),
            "modes": [{"T": np.asarray(m.T, np.float64).tolist(), "loglik": float(m.loglik), "gap": float(m.gap),
                       "probability": float(m.probability), "what": m.what} for m in o.modes],
            "position_spread_m": float(o.position_spread_m),
            "yaw_range_deg": None if o.yaw_range_deg is None else [float(v) for v in o.yaw_range_deg],
            "seen_through": float(o.seen_through),
            "elsewhere": float(o.elsewhere),
        } for o in posterior.objects],
    }


def parse_answer(value, K: int) -> Answer | None:
    """The ``answer`` entry of an estimator state for K objects (None: not settled) -> Answer. Raises ValueError
    naming what is malformed."""
    if value is None:
        return None
    where = "answer"
    _keys(value, ("scene", "loglik", "ties", "posterior"), where)
    scene = _poses(value["scene"], (K, 4, 4), f"{where}.scene")
    loglik = _number(value["loglik"], f"{where}.loglik", finite=False)
    ties = [_tie(t, K, f"{where}.ties[{i}]") for i, t in enumerate(_list(value["ties"], f"{where}.ties"))]
    post = value["posterior"]
    return Answer(scene, loglik, ties, None if post is None else parse_posterior(post, K, f"{where}.posterior"))


def parse_posterior(value, K: int, where: str = "posterior") -> Posterior:
    """A ``posterior_json`` for K objects -> Posterior; ValueError naming what is malformed."""
    _keys(value, ("temperature", "objects"), where)
    temperature = _number(value["temperature"], f"{where}.temperature")
    if temperature <= 0:
        raise ValueError(f"{where}.temperature must be > 0, got {temperature!r}")
    objects = _list(value["objects"], f"{where}.objects")
    if len(objects) != K:
        raise ValueError(f"{where}.objects must list the {K} objects, got {len(objects)}")
    return Posterior([_object(o, k, f"{where}.objects[{k}]") for k, o in enumerate(objects)], temperature)


def _object(value, k: int, where: str) -> ObjectPosterior:
    keys = ("obj", "modes", "position_spread_m", "yaw_range_deg")
    # Sessions saved before the chance of "elsewhere" was reported have neither entry: no doubt, as they showed.
    _keys(value, keys + ("seen_through", "elsewhere") if "elsewhere" in value else keys, where)
    elsewhere = _number(value.get("elsewhere", 0.0), f"{where}.elsewhere")
    seen_through = _number(value.get("seen_through", 0.0), f"{where}.seen_through")
    if not (0.0 <= elsewhere <= 1.0 and 0.0 <= seen_through <= 1.0):
        raise ValueError(f"{where}.elsewhere and .seen_through must lie in [0, 1], got {elsewhere!r} and "
                         f"{seen_through!r}")
    if value["obj"] != k or isinstance(value["obj"], bool):
        raise ValueError(f"{where}.obj must be {k} (objects in order), got {value['obj']!r}")
    modes = [_mode(m, f"{where}.modes[{j}]") for j, m in enumerate(_list(value["modes"], f"{where}.modes"))]
    if not modes:
        raise ValueError(f"{where}.modes is empty: the estimate is always a mode")
    p = np.array([m.probability for m in modes])
    if abs(p.sum() - 1.0) > 1e-6 or np.any(np.diff(p) > 1e-12):
        raise ValueError(f"{where}.modes must be probabilities summing to 1, most likely first, got {p.tolist()}")
    spread = _number(value["position_spread_m"], f"{where}.position_spread_m")
    if not 0.0 <= spread <= 1.0:
        raise ValueError(f"{where}.position_spread_m must lie in [0, 1] m, got {spread!r}")
    yaw = value["yaw_range_deg"]
    if yaw is not None:
        yaw = tuple(_number(v, f"{where}.yaw_range_deg") for v in _list(yaw, f"{where}.yaw_range_deg"))
        if len(yaw) != 2 or not -180.0 <= yaw[0] <= 0.0 <= yaw[1] <= 180.0:
            raise ValueError(f"{where}.yaw_range_deg must be [lo, hi] degrees with -180 <= lo <= 0 <= hi <= 180, "
                             f"got {list(yaw)}")
    return ObjectPosterior(k, modes, spread, yaw, seen_through, elsewhere)


def _mode(value, where: str) -> Mode:
    _keys(value, ("T", "loglik", "gap", "probability", "what"), where)
    probability = _number(value["probability"], f"{where}.probability")
    if not 0.0 <= probability <= 1.0:
        raise ValueError(f"{where}.probability must lie in [0, 1], got {probability!r}")
    return Mode(_poses(value["T"], (4, 4), f"{where}.T"), _number(value["loglik"], f"{where}.loglik"),
                _number(value["gap"], f"{where}.gap"), probability, _text(value["what"], f"{where}.what"))


def _tie(value, K: int, where: str) -> Tie:
    _keys(value, ("obj", "turn", "T", "gap"), where)
    obj = value["obj"]
    if isinstance(obj, bool) or not isinstance(obj, int) or not 0 <= obj < K:
        raise ValueError(f"{where}.obj must be an object index below {K}, got {obj!r}")
    return Tie(obj, _text(value["turn"], f"{where}.turn"), _poses(value["T"], (4, 4), f"{where}.T"),
               _number(value["gap"], f"{where}.gap"))


# Typed readers: a hand-edited value of the wrong type is reported by name.


def _keys(value, keys: tuple[str, ...], where: str) -> None:
    if not isinstance(value, dict):
        raise ValueError(f"{where} must be an object")
    if sorted(value) != sorted(keys):
        raise ValueError(f"{where} must have exactly the entries {list(keys)}, got {sorted(value)}")


def _list(value, where: str) -> list:
    if not isinstance(value, list):
        raise ValueError(f"{where} must be a list")
    return value


def _text(value, where: str) -> str:
    if not isinstance(value, str) or len(value) > 200:
        raise ValueError(f"{where} must be a short text")
    return value


def _number(value, where: str, finite: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or np.isnan(value) \
            or (finite and not np.isfinite(value)):
        raise ValueError(f"{where} must be a {'finite ' if finite else ''}number, got {value!r}")
    return float(value)


def _poses(value, shape: tuple, where: str) -> np.ndarray:
    """Rigid poses of ``shape`` (a reflection or a bad bottom row is refused)."""
    try:
        T = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as e:
        raise ValueError(f"{where} must be finite numbers of shape {shape}") from e
    if T.shape != shape or not np.all(np.isfinite(T)):
        raise ValueError(f"{where} must be finite numbers of shape {shape}, got shape {T.shape}")
    try:
        return check_rigid(T, where)
    except InputError as e:
        raise ValueError(e.problem) from e
