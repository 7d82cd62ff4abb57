"""Lost tracking: which objects the carried scene no longer explains, and the words a frame's status is said in."""

from __future__ import annotations

import numpy as np


def lost_objects(badness: np.ndarray, before: np.ndarray, floor: float, rise: float) -> np.ndarray:
    """Per object, whether its carried pose is lost: its badness on the new frame (``badness`` (K,) in [0, 1],
    ``scenepoints.object_badness``: the share of its visible surface the sensor sees through) above ``floor`` and
    above its badness on the previous frame (``before`` (K,)) plus ``rise`` -> (K,) bool. Relative to the previous
    frame, so that an object that never fitted well (a model unlike the real object, much of it out of view) is not
    lost again on every frame."""
    return (badness > floor) & (badness > np.asarray(before) + rise)


def status_words(searched: int, found: int) -> str:
    """A tracked frame's status in words: "tracked", "2 objects re-found", "1 object re-found, 1 still lost"."""
    if searched == 0:
        return "tracked"
    words = f"{found} object{'s' if found != 1 else ''} re-found" if found else ""
    missing = searched - found
    if missing:
        words += (", " if words else "") + f"{missing} object{'s' if missing != 1 else ''} still lost"
    return words
