"""The engine's results pipe, stood in for by a list: the engine tests drive an ``Engine`` in the test's process
and read what it sent."""

from __future__ import annotations


class Inbox(list):
    """Stands in for the engine's results pipe: every message, in order."""

    def put(self, msg) -> None:
        self.append(msg)

    def of(self, kind) -> list:
        return [m for m in self if isinstance(m, kind)]
