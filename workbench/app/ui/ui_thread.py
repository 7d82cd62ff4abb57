"""The UI side's one owner: a thread that runs every change to the GUI and the 3D view, one at a time, in the
order they were posted.

viser calls GUI callbacks on its own thread pool, the engine's messages arrive on the reader thread, and timers
fire on theirs; all of them hand their work to ``UiThread`` (``call``, ``post``, ``later``) instead of taking a
lock, so the modules of ``app/ui`` read and write their handles without one. Writing a handle on the UI thread
fires its callbacks at once in the same thread: ``call`` runs those inline (a queue would deadlock on itself).
"""

from __future__ import annotations

import functools
import heapq
import itertools
import logging
import queue
import threading
import time
from concurrent.futures import Future
from typing import Callable

log = logging.getLogger(__name__)


class Later:
    """A task due later (``UiThread.later``); ``cancel()`` on the UI thread drops it for sure."""

    def __init__(self, fn: Callable[[], None]):
        self.fn, self.cancelled = fn, False

    def cancel(self) -> None:
        self.cancelled = True


class UiThread:
    def __init__(self, name: str = "workbench-ui"):
        self._tasks: queue.SimpleQueue = queue.SimpleQueue()
        self._later: list = []  # a heap of (due, n, Later); only the UI thread touches it
        self._count = itertools.count()
        self._waiters: list[threading.Event] = []  # ``wait_until``'s, set after every task
        self._stopped = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def here(self) -> bool:
        """Whether the caller runs on the UI thread."""
        return threading.current_thread() is self._thread

    def post(self, fn: Callable, *args) -> None:
        """Run ``fn(*args)`` on the UI thread after what is queued already; do not wait for it."""
        if not self._stopped:
            self._tasks.put((fn, args, {}, None))

    def call(self, fn: Callable, *args, **kwargs):
        """Run ``fn(*args, **kwargs)`` on the UI thread and return its result (or raise its exception): inline
        when called there, else queued and waited for. Once stopped, nothing runs and the answer is None."""
        if self.here():
            return fn(*args, **kwargs)
        if self._stopped:
            return None
        done: Future = Future()
        self._tasks.put((fn, args, kwargs, done))
        while True:
            try:
                return done.result(timeout=0.5)
            except TimeoutError:
                if not self._thread.is_alive():  # stopped while this waited
                    return None

    def callback(self, fn: Callable) -> Callable:
        """A viser callback that runs ``fn(event)`` on the UI thread. Its caller waits: a handle written from
        another thread (a test, as another tab would) has had its effect once the write returns."""
        return lambda event: self.call(fn, event)

    def later(self, delay: float, fn: Callable[[], None]) -> Later:
        """Run ``fn()`` on the UI thread ``delay`` seconds from now, unless cancelled first. Call on the UI thread."""
        assert self.here(), "UiThread.later is for the UI thread"
        task = Later(fn)
        heapq.heappush(self._later, (time.monotonic() + delay, next(self._count), task))
        return task

    def wait_until(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Block until ``predicate()`` holds, or the timeout. It is checked in the caller's thread (it may drive
        a browser, whose objects belong to that thread): at once, after each task the UI thread runs, and at least
        every half second."""
        ran = threading.Event()
        self.call(self._waiters.append, ran)
        try:
            deadline = time.monotonic() + timeout
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                ran.wait(min(left, 0.5))
                ran.clear()
            return True
        finally:
            self.call(lambda: ran in self._waiters and self._waiters.remove(ran))

    def stop(self, timeout: float = 5.0) -> None:
        """Run what is queued, then end the thread; later posts and calls are dropped."""
        self._stopped = True
        self._tasks.put(None)
        if not self.here():
            self._thread.join(timeout)

    def _loop(self) -> None:
        while True:
            while self._later and self._later[0][0] <= time.monotonic():
                task = heapq.heappop(self._later)[2]
                if not task.cancelled:
                    self._run(task.fn, (), {}, None)
            wait = max(0.0, self._later[0][0] - time.monotonic()) if self._later else None
            try:
                item = self._tasks.get(timeout=wait)
            except queue.Empty:
                continue
            if item is None:
                return
            self._run(*item)

    def _run(self, fn: Callable, args: tuple, kwargs: dict, done: Future | None) -> None:
        if done is not None and not done.set_running_or_notify_cancel():
            return
        try:
            result = fn(*args, **kwargs)
        except BaseException as err:  # the UI thread goes on: one callback's bug must not stop the others
            if done is not None:
                done.set_exception(err)
            else:
                log.exception("UI task %s", getattr(fn, "__qualname__", fn))
        else:
            if done is not None:
                done.set_result(result)
        for ran in self._waiters:
            ran.set()


def on_ui_thread(method: Callable) -> Callable:
    """A method of an object with a ``ui`` (``UiThread``) that runs there, whichever thread calls it."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        return self.ui.call(method, self, *args, **kwargs)

    return wrapper
