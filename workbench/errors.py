"""The one error type users see for bad input: it names the file and the problem."""

from __future__ import annotations

from pathlib import Path


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
