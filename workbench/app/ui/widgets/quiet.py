"""Telling the server's own GUI writes from the user's edits.

Assigning ``handle.value`` on the server calls the handle's ``on_update`` callbacks at once, in the assigning
thread. When the server *shows* a value (a label moved by its gizmo, a session's settings restored), those callbacks
must not send the value back to the engine as if the user had typed it: inside ``with quiet:`` they see
``quiet.active`` and return. The flag is per thread: the server writes on the UI thread, where those callbacks run
inline, and a user's edit queued meanwhile runs after the write, when the flag is down again.
"""

from __future__ import annotations

import threading


class Quiet:
    def __init__(self) -> None:
        self._local = threading.local()

    @property
    def active(self) -> bool:
        return getattr(self._local, "depth", 0) > 0

    def __enter__(self) -> "Quiet":
        self._local.depth = getattr(self._local, "depth", 0) + 1
        return self

    def __exit__(self, *exc) -> None:
        self._local.depth -= 1
