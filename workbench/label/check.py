"""A frame's labels checked against its depth, with no ground truth: where each labelled object is the nearest
thing drawn, does the sensor see its surface there?

Per object, over the pixels of its silhouette where it is in front of every other label and the sensor has a
reading (``seen``):
- ``agree``: the share within ``CheckConfig.agree_m`` of the label's surface (a few millimetres: the sensor's
  noise and the dataset's own labels' error, measured in the docs' journal);
- ``through``: the share where the sensor sees *past* the label by more than ``tau_m`` (nothing is where the label
  says, as where an object was taken out, or the label sits off its object and covers the table beyond it);
- ``front``: the share where something is *nearer* than the label by more than ``tau_m`` (an unlabelled occluder,
  or the label lies behind the surface the camera sees);
``1 - agree`` is then the label's visible-surface discrepancy (VSD's step cost at ``agree_m``, on what is seen).
An object with fewer than ``min_pixels`` seen pixels cannot be checked in that frame (hidden, or out of view): its
row says so and it is never flagged. A frame is flagged when one of its checked objects agrees on less than
``min_agree`` of its seen pixels.

Depths are camera z in metres on one pixel grid (the problem's render grid), 0 where there is none.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.errors import InputError


@dataclass(frozen=True)
class CheckConfig:
    """``agree_m``: a seen pixel agrees within this of the label's surface (metres); ``tau_m``: beyond this the
    sensor sees past (or in front of) the label; ``min_agree``: an object agreeing on less than this share of its
    seen pixels flags its frame; ``min_pixels``: fewer seen pixels than this and the object is not checked."""

    agree_m: float = 0.01
    tau_m: float = 0.02
    min_agree: float = 0.5
    min_pixels: int = 30

    def validate(self) -> None:
        if not 0 < self.agree_m <= self.tau_m:
            raise InputError("check", f"needs 0 < agree ({self.agree_m} m) <= tau ({self.tau_m} m)")
        if not 0 <= self.min_agree <= 1:
            raise InputError("check", f"min_agree must lie in [0, 1], got {self.min_agree}")
        if self.min_pixels < 1:
            raise InputError("check", f"min_pixels must be >= 1, got {self.min_pixels}")


@dataclass(frozen=True)
class ObjectCheck:
    """One labelled object in one frame: ``pixels`` seen (its silhouette in front of the other labels, with a
    reading), the shares ``agree``, ``through`` and ``front`` of them (see the module), and whether it is
    ``checked`` (enough pixels) and ``flagged``."""

    obj_id: int
    pixels: int
    agree: float
    through: float
    front: float
    checked: bool
    flagged: bool

    @property
    def reason(self) -> str:
        """Why it is flagged, in words ("" when it is not)."""
        if not self.flagged:
            return ""
        if self.through >= self.front:
            return f"the depth sees past it on {self.through:.0%} of its pixels"
        return f"something is in front of it on {self.front:.0%} of its pixels"

    def to_dict(self) -> dict:
        return {"obj_id": self.obj_id, "pixels": self.pixels, "agree": round(self.agree, 4),
                "through": round(self.through, 4), "front": round(self.front, 4), "checked": self.checked,
                "flagged": self.flagged}


def seen_masks(alone: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """Where each label is the nearest label drawn and the sensor has a reading. ``alone``: (K, h, w) each object's
    depth drawn alone (0 = not drawn there); ``observed``: (h, w) -> (K, h, w) bool."""
    alone = np.asarray(alone, dtype=np.float64)
    drawn = alone > 0
    nearest = np.where(drawn, alone, np.inf).min(axis=0)
    return drawn & (alone <= nearest[None]) & (np.asarray(observed) > 0)[None]


def object_shares(alone: np.ndarray, observed: np.ndarray, config: CheckConfig) -> np.ndarray:
    """Per object, (seen pixels, agree, through, front) as (K, 4) float64 (shares 0 where nothing is seen).
    ``alone``: (K, h, w) each label's depth drawn alone, ``observed``: (h, w), metres, 0 = none."""
    alone = np.asarray(alone, dtype=np.float64)
    observed = np.asarray(observed, dtype=np.float64)
    seen = seen_masks(alone, observed)
    residual = observed[None] - alone  # > 0: the sensor sees past the label
    out = np.zeros((len(alone), 4))
    for k in range(len(alone)):
        r = residual[k][seen[k]]
        n = r.size
        out[k, 0] = n
        if n:
            out[k, 1:] = (np.mean(np.abs(r) <= config.agree_m), np.mean(r > config.tau_m),
                          np.mean(r < -config.tau_m))
    return out


def check_objects(obj_ids: list[int], alone: np.ndarray, observed: np.ndarray,
                  config: CheckConfig = CheckConfig()) -> list[ObjectCheck]:
    """Each label of one frame checked (``object_shares``) -> one ``ObjectCheck`` per entry of ``obj_ids``; an
    object not labelled in the frame has an all-zero depth in ``alone`` and comes back unchecked."""
    shares = object_shares(alone, observed, config)
    out = []
    for obj_id, (n, agree, through, front) in zip(obj_ids, shares):
        checked = n >= config.min_pixels
        out.append(ObjectCheck(int(obj_id), int(n), float(agree), float(through), float(front), bool(checked),
                               bool(checked and agree < config.min_agree)))
    return out


def render_alone(renderer, T_world_obj: np.ndarray, present: np.ndarray) -> np.ndarray:
    """Each present label drawn alone by ``renderer`` (a ``DepthRenderer`` of the frame's problem): ``T_world_obj``
    (K, 4, 4) table frame, ``present`` (K,) bool -> (K, h, w) float32 metres (all 0 for an absent object)."""
    K = len(T_world_obj)
    T = np.where(np.asarray(present)[:, None, None], T_world_obj, np.eye(4))  # an absent label's pose is ignored
    drawn = np.eye(K, dtype=bool) & np.asarray(present, dtype=bool)[None]
    return renderer.render(np.repeat(T[None], K, axis=0), drawn=drawn)


def worst(checks: list[ObjectCheck]) -> float | None:
    """A frame's worst checked object's agreement (None when none could be checked): the timeline's colour."""
    shares = [c.agree for c in checks if c.checked]
    return min(shares) if shares else None
