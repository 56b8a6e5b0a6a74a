"""The one way values from foreign threads reach the event loop (janus lesson).

Middleware callbacks may run on the middleware's own thread (the ROS 2 executor). Scheduling a
call per value would swamp the loop; instead callbacks append to one bounded deque and the first
append of a burst schedules a single drain with ``call_soon_threadsafe``. Calls made on the loop
thread itself (the in-process bus) skip the hop entirely.
"""

from __future__ import annotations

import asyncio
import threading
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

from rlbridge.adapters.base import ValuesCallback

_Item = tuple[Callable[[Sequence[Any]], None], Sequence[Any]]


class LoopHandoff:
    """Batches callbacks from other threads into the loop; drops (and counts) past ``limit``."""

    def __init__(self, loop: asyncio.AbstractEventLoop, limit: int = 65536) -> None:
        self._loop = loop
        self._loop_thread = threading.get_ident()
        self._pending: deque[_Item] = deque()
        self._lock = threading.Lock()
        self._scheduled = False
        self._limit = limit
        self.dropped_batches = 0

    def wrap(self, fn: Callable[[Sequence[Any]], None]) -> ValuesCallback:
        """A callback that runs ``fn`` on the loop thread, whatever thread calls it."""
        loop_thread = self._loop_thread

        def callback(values: Sequence[Any]) -> None:
            if threading.get_ident() == loop_thread:
                fn(values)
            else:
                self._push(fn, values)

        return callback

    def _push(self, fn: Callable[[Sequence[Any]], None], values: Sequence[Any]) -> None:
        with self._lock:
            if len(self._pending) >= self._limit:
                self.dropped_batches += 1
                return
            self._pending.append((fn, values))
            if self._scheduled:
                return
            self._scheduled = True
        try:
            self._loop.call_soon_threadsafe(self._drain)
        except RuntimeError:  # loop closed during shutdown: nothing left to deliver to
            with self._lock:
                self._pending.clear()

    def _drain(self) -> None:
        with self._lock:
            items = list(self._pending)
            self._pending.clear()
            self._scheduled = False
        for fn, values in items:
            fn(values)
