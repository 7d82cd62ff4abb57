"""A sequence's position as a session keeps it (``SessionState.sequence``): the processed frames with their timeline
entries, the frame on show, and the settings a frame estimated from scratch runs with (the panel's; a
tracked frame's run has its own). Plain JSON, so that the session file stays readable; read back with every field
checked, so that a hand-edited file is an InputError naming it, never a broken timeline.

The session holds the run of the frame on show only: the other frames come back as timeline entries (status,
seconds, positions, confidences), not as runs.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from workbench.app import protocol as p
from workbench.errors import InputError
from workbench.inference.config import EstimatorConfig
from workbench.inference.search.moves.registry import MoveMix
from workbench.label.sequence import SequenceLabels, labels_json, parse_labels
from workbench.sessions.document import config_from_dict


@dataclass(frozen=True)
class SequenceRecord:
    """``frames``: the processed frames in order (``held`` False: their runs are not in the session);
    ``current``: the image id on show, the session's frame; ``config``: the panel's settings; ``labels``: the
    sequence labels the Label tab holds, so that a session keeps them whether they were written or not."""

    frames: list[p.SequenceFrame]
    current: int
    config: EstimatorConfig
    labels: SequenceLabels | None = None  # the sequence labels on hand (``label.sequence``), saved or not


def record_json(record: SequenceRecord) -> dict:
    """-> the plain JSON object a session stores (positions in m, NaN where unknown)."""
    return {
        "current": record.current,
        "config": {k: v.as_dict() if isinstance(v, MoveMix) else v for k, v in asdict(record.config).items()},
        "frames": [{"im_id": f.im_id, "status": f.status, "seconds": f.seconds, "motion": f.motion,
                    "positions": np.asarray(f.positions, dtype=np.float64).tolist(),
                    "confidences": np.asarray(f.confidences, dtype=np.float64).tolist()} for f in record.frames],
        **({} if record.labels is None else {"labels": labels_json(record.labels)}),
    }


def parse_record(data: dict, path: Path, n_objects: int, im_id: int) -> SequenceRecord:
    """A session's ``sequence`` entry for its frame ``im_id`` of ``n_objects`` objects -> the record; InputError
    naming the session file ``path`` and the entry at fault."""
    try:
        config = config_from_dict(EstimatorConfig, data["config"], "sequence.config")
        config.validate("sequence.config.")
        frames = [_frame(f, n_objects, f"sequence.frames[{i}]") for i, f in enumerate(data["frames"])]
        current = data["current"]
        labels = None if data.get("labels") is None else parse_labels(data["labels"])
    except InputError as err:
        raise InputError(path, f"{err.path}: {err.problem}" if err.path else err.problem) from err
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(path, f"malformed sequence entry ({type(err).__name__}: {err})") from err
    ids = [f.im_id for f in frames]
    if not ids or ids != sorted(set(ids)):
        raise InputError(path, f"sequence.frames must list processed frames in increasing order, got {ids}")
    if labels is not None and len(labels.objects) != n_objects:
        raise InputError(path, f"sequence.labels must label the frame's {n_objects} objects, got "
                               f"{len(labels.objects)}")
    if current != im_id or current not in ids:
        raise InputError(path, f"sequence.current is {current!r}: it must be the session's frame {im_id}, one of "
                               f"the processed frames {ids}")
    return SequenceRecord([replace(f, held=False) for f in frames], current, config, labels)


def _frame(f: dict, n_objects: int, where: str) -> p.SequenceFrame:
    """One frame's entry, checked."""
    positions = np.asarray(f["positions"], dtype=np.float64)
    confidences = np.asarray(f["confidences"], dtype=np.float64)
    if positions.shape != (n_objects, 3) or confidences.shape != (n_objects,):
        raise ValueError(f"{where}: positions must be {n_objects} x 3 numbers and confidences {n_objects}, got "
                         f"shapes {positions.shape} and {confidences.shape}")
    if np.any(confidences < 0) or np.any(confidences > 1):
        raise ValueError(f"{where}: confidences must lie in [0, 1] (or be NaN)")
    im_id, seconds = f["im_id"], float(f["seconds"])
    if not isinstance(im_id, int) or isinstance(im_id, bool) or im_id < 0:
        raise ValueError(f"{where}.im_id must be an image id (a whole number >= 0), got {im_id!r}")
    if not isinstance(f["status"], str) or not isinstance(f["motion"], str) or not seconds >= 0:
        raise ValueError(f"{where}: status and motion must be text and seconds a number >= 0")
    return p.SequenceFrame(im_id, f["status"], seconds, f["motion"], positions, confidences)
