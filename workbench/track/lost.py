"""Lost tracking: which objects the carried scene no longer explains, and the words a frame's status is said in."""

from __future__ import annotations

import numpy as np

NO_DEPTH = "lost: no depth"  # a frame whose depth holds (almost) nothing: the posterior carried through it unchanged
RECOVERED = "recovered"  # the first frame tracked after a lost one


def lost_objects(badness: np.ndarray, before: np.ndarray, floor: float, rise: float) -> np.ndarray:
    """Per object, whether its carried pose is lost: its badness on the new frame (``badness`` (K,) in [0, 1],
    ``scenepoints.object_badness``: the share of its visible surface the sensor sees through) above ``floor`` and
    above its badness on the previous frame (``before`` (K,)) plus ``rise`` -> (K,) bool. Relative to the previous
    frame, so that an object that never fitted well (a model unlike the real object, much of it out of view) is not
    lost again on every frame."""
    return (badness > floor) & (badness > np.asarray(before) + rise)


def _objects(n: int, what: str) -> str:
    return f"{n} object{'s' if n != 1 else ''} {what}"


def status_words(searched: int, found: int, recovered: int = 0) -> str:
    """A tracked frame's status in words: "tracked", "2 objects re-found", "1 object re-found, 1 still lost",
    "1 object recovered" (an object lost on the frame before, explained again where it was last found)."""
    parts = [_objects(recovered, "recovered")] if recovered else []
    if found:
        parts.append(_objects(found, "re-found"))
    if searched - found:
        parts.append(_objects(searched - found, "still lost"))
    return ", ".join(parts) if parts else "tracked"
