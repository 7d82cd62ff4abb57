"""The one error type users see for bad input: it names the file and the problem; and the check of a whole-number
setting, which every config's ``validate`` and the command line share."""

from __future__ import annotations

from pathlib import Path

import numpy as np


class InputError(ValueError):
    """Bad user input (missing or corrupt file, wrong units, impossible parameter).

    ``path`` is the file (or setting) at fault; ``problem`` says what is wrong with it in words a user can act on.
    """

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)

    def __reduce__(self):
        # Rebuilt from (path, problem), not from the joined message: Ray hands a frame task's error back pickled.
        return type(self), (self.path, self.problem)


def is_whole_number(value) -> bool:
    """An int (numpy's too), not a bool: ``True`` is no count."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def check_count(value, where: str, low: int = 1, high: int | None = None) -> int:
    """A whole-number setting within [low, high], else InputError naming ``where``."""
    if not is_whole_number(value) or value < low or (high is not None and value > high):
        span = f"from {low} to {high}" if high is not None else f">= {low}"
        raise InputError(where, f"must be a whole number {span}, got {value!r}")
    return int(value)
