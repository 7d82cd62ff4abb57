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

from workbench.inference.answer.hidden import HidingRegion
from workbench.inference.answer.posterior import Mode, ObjectPosterior, Posterior
from workbench.inference.answer.settle import Tie
from workbench.io import readers as read


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
    spread (m), open heading range (degrees, or null) and, for a hidden object, its hiding region (places m and
    their probabilities and gaps); the temperature, and the stage a budget cut short (only where one did)."""
    cut = {} if posterior.cut_short is None else {"cut_short": posterior.cut_short}
    return {
        **cut,
        "temperature": float(posterior.temperature),
        "objects": [{
            "obj": int(o.obj),
            "modes": [{"T": np.asarray(m.T, np.float64).tolist(), "loglik": float(m.loglik), "gap": float(m.gap),
                       "probability": float(m.probability), "what": m.what} for m in o.modes],
            "position_spread_m": float(o.position_spread_m),
            "yaw_range_deg": None if o.yaw_range_deg is None else [float(v) for v in o.yaw_range_deg],
            "seen_through": float(o.seen_through),
            "elsewhere": float(o.elsewhere),
            **({} if o.hiding is None else {"hiding": {
                "places": np.asarray(o.hiding.places, np.float64).tolist(),
                "probabilities": np.asarray(o.hiding.probabilities, np.float64).tolist(),
                "gaps": np.asarray(o.hiding.gaps, np.float64).tolist()}}),
        } for o in posterior.objects],
    }


def parse_answer(value, K: int) -> Answer | None:
    """The ``answer`` entry of an estimator state for K objects (None: not settled) -> Answer. Raises ValueError
    naming what is malformed."""
    if value is None:
        return None
    where = "answer"
    read.exact_keys(value, ("scene", "loglik", "ties", "posterior"), where)
    scene = read.poses(value["scene"], (K, 4, 4), f"{where}.scene")
    loglik = read.quantity(value["loglik"], f"{where}.loglik", finite=False)
    ties = [_tie(t, K, f"{where}.ties[{i}]") for i, t in enumerate(read.json_list(value["ties"], f"{where}.ties"))]
    post = value["posterior"]
    return Answer(scene, loglik, ties, None if post is None else parse_posterior(post, K, f"{where}.posterior"))


def parse_posterior(value, K: int, where: str = "posterior") -> Posterior:
    """A ``posterior_json`` for K objects -> Posterior; ValueError naming what is malformed."""
    read.exact_keys(value, ("temperature", "objects", "cut_short") if "cut_short" in value
                    else ("temperature", "objects"), where)
    cut_short = None if "cut_short" not in value else read.short_text(value["cut_short"], f"{where}.cut_short")
    temperature = read.quantity(value["temperature"], f"{where}.temperature")
    if temperature <= 0:
        raise ValueError(f"{where}.temperature must be > 0, got {temperature!r}")
    objects = read.json_list(value["objects"], f"{where}.objects")
    if len(objects) != K:
        raise ValueError(f"{where}.objects must list the {K} objects, got {len(objects)}")
    return Posterior([_object(o, k, f"{where}.objects[{k}]") for k, o in enumerate(objects)], temperature,
                     cut_short=cut_short)


def _object(value, k: int, where: str) -> ObjectPosterior:
    keys = ("obj", "modes", "position_spread_m", "yaw_range_deg")
    # Sessions saved before the chance of "elsewhere" was reported have neither entry: no doubt, as they showed.
    if "elsewhere" in value:
        keys += ("seen_through", "elsewhere")
    read.exact_keys(value, keys + ("hiding",) if "hiding" in value else keys, where)
    hiding = None if "hiding" not in value else _hiding(value["hiding"], f"{where}.hiding")
    elsewhere = read.quantity(value.get("elsewhere", 0.0), f"{where}.elsewhere")
    seen_through = read.quantity(value.get("seen_through", 0.0), f"{where}.seen_through")
    if not (0.0 <= elsewhere <= 1.0 and 0.0 <= seen_through <= 1.0):
        raise ValueError(f"{where}.elsewhere and .seen_through must lie in [0, 1], got {elsewhere!r} and "
                         f"{seen_through!r}")
    if value["obj"] != k or isinstance(value["obj"], bool):
        raise ValueError(f"{where}.obj must be {k} (objects in order), got {value['obj']!r}")
    modes = [_mode(m, f"{where}.modes[{j}]") for j, m in enumerate(read.json_list(value["modes"], f"{where}.modes"))]
    if not modes:
        raise ValueError(f"{where}.modes is empty: the estimate is always a mode")
    p = np.array([m.probability for m in modes])
    if abs(p.sum() - 1.0) > 1e-6 or np.any(np.diff(p) > 1e-12):
        raise ValueError(f"{where}.modes must be probabilities summing to 1, most likely first, got {p.tolist()}")
    spread = read.quantity(value["position_spread_m"], f"{where}.position_spread_m")
    if not 0.0 <= spread <= 1.0:
        raise ValueError(f"{where}.position_spread_m must lie in [0, 1] m, got {spread!r}")
    yaw = value["yaw_range_deg"]
    if yaw is not None:
        yaw = tuple(read.quantity(v, f"{where}.yaw_range_deg") for v in read.json_list(yaw, f"{where}.yaw_range_deg"))
        if len(yaw) != 2 or not -180.0 <= yaw[0] <= 0.0 <= yaw[1] <= 180.0:
            raise ValueError(f"{where}.yaw_range_deg must be [lo, hi] degrees with -180 <= lo <= 0 <= hi <= 180, "
                             f"got {list(yaw)}")
    return ObjectPosterior(k, modes, spread, yaw, seen_through, elsewhere, hiding)


def _hiding(value, where: str) -> HidingRegion:
    read.exact_keys(value, ("places", "probabilities", "gaps"), where)
    places = read.json_list(value["places"], f"{where}.places")
    places = read.finite_array(places, (len(places), 3), np.float64, f"{where}.places")
    p = read.finite_array(value["probabilities"], (len(places),), np.float64, f"{where}.probabilities")
    if not len(p) or np.any(p < 0) or abs(p.sum() - 1.0) > 1e-6:
        raise ValueError(f"{where}.probabilities must be one per place, summing to 1, got {p.tolist()}")
    return HidingRegion(places, p, read.finite_array(value["gaps"], (len(places),), np.float64, f"{where}.gaps"))


def _mode(value, where: str) -> Mode:
    read.exact_keys(value, ("T", "loglik", "gap", "probability", "what"), where)
    probability = read.quantity(value["probability"], f"{where}.probability")
    if not 0.0 <= probability <= 1.0:
        raise ValueError(f"{where}.probability must lie in [0, 1], got {probability!r}")
    return Mode(read.poses(value["T"], (4, 4), f"{where}.T"), read.quantity(value["loglik"], f"{where}.loglik"),
                read.quantity(value["gap"], f"{where}.gap"), probability,
                read.short_text(value["what"], f"{where}.what"))


def _tie(value, K: int, where: str) -> Tie:
    read.exact_keys(value, ("obj", "turn", "T", "gap"), where)
    obj = value["obj"]
    if isinstance(obj, bool) or not isinstance(obj, int) or not 0 <= obj < K:
        raise ValueError(f"{where}.obj must be an object index below {K}, got {obj!r}")
    return Tie(obj, read.short_text(value["turn"], f"{where}.turn"), read.poses(value["T"], (4, 4), f"{where}.T"),
               read.quantity(value["gap"], f"{where}.gap"))
