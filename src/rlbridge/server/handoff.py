"""The one way values from foreign threads reach the event loop (janus lesson).

Middleware callbacks may run on the middleware's own thread (the ROS 2 executor). Scheduling a
call per value would swamp the loop; instead callbacks append to one bounded deque and the first
append of a burst schedules a single drain with ``call_soon_threadsafe``. Calls made on the loop
thread itself (the in-process bus) skip the hop entirely.

Each batch is stamped (CLOCK_REALTIME) when the middleware's callback delivers it, on the
callback's thread, before any queueing here: a value's stamp and age then measure from the
middleware's delivery, not from when the loop got round to forwarding it.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

from rlbridge.adapters.base import ValuesCallback

StampedFn = Callable[[Sequence[Any], int], None]
_Item = tuple[StampedFn, Sequence[Any], int]


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

    def wrap(self, fn: StampedFn) -> ValuesCallback:
        """A callback that runs ``fn(values, stamp_ns)`` on the loop thread, from any thread."""
        loop_thread = self._loop_thread

        def callback(values: Sequence[Any]) -> None:
            stamp = time.time_ns()
            if threading.get_ident() == loop_thread:
                fn(values, stamp)
            else:
                self._push(fn, values, stamp)

        return callback

    def _push(self, fn: StampedFn, values: Sequence[Any], stamp: int) -> None:
        with self._lock:
            if len(self._pending) >= self._limit:
                self.dropped_batches += 1
                return
            self._pending.append((fn, values, stamp))
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
        for fn, values, stamp in items:
            fn(values, stamp)
