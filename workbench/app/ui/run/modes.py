"""The posterior per object (``inference.answer.posterior``) in words, for every part of the workbench that shows
it: the 3D view's mode labels and legend, the Inspect tab's table, the Label tab's choice of mode; and the labelled
scene made of the modes chosen there (computed in the engine process)."""

from __future__ import annotations

import numpy as np

from workbench.app.ui.widgets.colors import named
from workbench.app.ui.widgets.markdown import escape
from workbench.inference.answer.posterior import DOUBTFUL, Mode, ObjectPosterior, Posterior, hiding_text


def chance(o: ObjectPosterior, mode: Mode) -> float:
    """``mode``'s probability among all of object ``o``'s chances: its modes share what ``elsewhere`` leaves, so that
    the modes and elsewhere add up to 1 as shown (``Mode.probability`` is given that the object was found)."""
    return mode.probability * (1.0 - o.elsewhere)


def mode_label(o: ObjectPosterior, mode: Mode) -> str:
    """A mode of object ``o`` in words: "p = 0.31 turned over its x axis"."""
    return f"p = {chance(o, mode):.2f} {mode.what}"


def yaw_text(o: ObjectPosterior) -> str:
    """The open heading, e.g. "heading open −60° … +90°", or ""."""
    if o.yaw_range_deg is None:
        return ""
    lo, hi = o.yaw_range_deg
    return f"heading open {lo:+.0f}° … {hi:+.0f}°".replace("-", "−")


def confidence_text(o: ObjectPosterior) -> str:
    """An object's confidence: its top mode's ``chance``, the open heading if any, and the chance that it is
    elsewhere when that is at least ``posterior.DOUBTFUL`` or, for a hidden object, how many places it may be in:
    "p = 0.84", "p = 1.00, heading open −60° … +90°", "p = 0.38, elsewhere 0.62", "p = 0.03, hidden: one of 37
    places"."""
    yaw = yaw_text(o)
    doubt = (f"hidden: one of {len(o.hiding.places)} places" if o.hiding is not None
             else f"elsewhere {o.elsewhere:.2f}" if o.elsewhere >= DOUBTFUL else "")
    return ", ".join([f"p = {chance(o, o.modes[0]):.2f}", *(t for t in (yaw, doubt) if t)])


def confidences(posterior: Posterior | None, n_objects: int) -> list[str]:
    """Per object (``n_objects``) its ``confidence_text``, "" for every object without a posterior."""
    out = [""] * n_objects
    for o in posterior.objects if posterior is not None else []:
        if 0 <= o.obj < n_objects:
            out[o.obj] = confidence_text(o)
    return out


def mode_option(j: int, o: ObjectPosterior, mode: Mode) -> str:
    """One entry of the Label tab's choice of object ``o``'s mode: "mode 2 · p = 0.38 · turned over its x axis"."""
    return f"mode {j + 1} · p = {chance(o, mode):.2f} · {mode.what}"


NO_POSTERIOR = ("<small>No posterior yet: it is computed when the run finishes (iteration budget or convergence), "
                "or when the best estimate is taken as label; the paper's search has none.</small>")


def posterior_markdown(posterior: Posterior | None, names: list[str], iteration: int) -> str:
    """The Inspect tab's table: per object (``names``: display names by index) the top mode's probability, the
    position spread, the open heading and the other modes."""
    if posterior is None:
        return NO_POSTERIOR
    rows = []
    for o in posterior.objects:
        name = named(o.obj, names[o.obj] if o.obj < len(names) else f"object {o.obj}")
        others = "<br>".join(escape(mode_label(o, m)) for m in o.modes[1:]) or "—"  # one line each
        where = escape(hiding_text(o.hiding)) if o.hiding is not None else \
            f"{o.elsewhere:.2f} ({100 * o.seen_through:.0f} %)"
        rows.append(f"| {name} | {chance(o, o.modes[0]):.2f} | {others} | {where} | {o.position_spread_m * 1000:.1f} | "
                    f"{yaw_text(o).removeprefix('heading open ') or '—'} |")
    return (f"**Posterior** of the settled estimate · iteration {iteration}\n\n"
            "| object | p | other modes | elsewhere | spread mm | heading |\n"
            "|---|---:|---|---:|---:|---|\n"
            + "\n".join(rows)
            + f"\n\n<small>per object, the estimate (*p*), the other modes and *elsewhere* add up to 1; other modes "
              f"are drawn as ghosts in the 3D view; probabilities at temperature {posterior.temperature:g}; "
              f"*elsewhere*: the chance that it is none of its modes, from the share of its surface the sensor sees "
              f"through (in brackets), or for an object the sensor sees none of, the places it may hide in (dots in "
              f"the 3D view); *spread*: of its position; *heading*: the range of turns about the vertical left "
              f"open</small>")


def scene_with_modes(scene: np.ndarray, posterior: Posterior | None, modes: tuple[int, ...],
                     names: list[str]) -> tuple[np.ndarray, list[str]]:
    """The settled ``scene`` (K, 4, 4) with object k put in its mode ``modes[k]`` (0, or an index past its modes:
    the estimate itself) -> (the scene, one line per object so placed: "obj_000006: mode 2 (p = 0.16, where
    particles put it)")."""
    out, notes = np.array(scene, dtype=np.float64), []
    if posterior is None:
        return out, notes
    for o in posterior.objects:
        j = modes[o.obj] if o.obj < len(modes) else 0
        if 0 < j < len(o.modes):
            m = o.modes[j]
            out[o.obj] = m.T
            notes.append(f"{names[o.obj]}: mode {j + 1} (p = {m.probability:.2f}, {m.what})")
    return out, notes
