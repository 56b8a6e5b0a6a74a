"""The one way values from foreign threads reach the event loop (janus lesson).

Middleware callbacks may run on the middleware's own thread (the ROS 2 executor). Scheduling a
call per value would swamp the loop; instead callbacks append to one bounded deque and the first
append of a burst schedules a single drain with ``call_soon_threadsafe``. Calls made on the loop
thread itself (the in-process bus) skip the hop entirely.

Each batch is stamped (CLOCK_REALTIME) when the middleware's callback delivers it, on the
callback's thread, before any queueing here: a value's stamp and age then measure from the
middleware's delivery, not from when the loop got round to forwarding it.

A batch that finds the deque full (the loop is that far behind) is dropped, and its values
are counted for the channel it was for: the callback's ``on_drop`` gets their number on the
loop thread, with the next drain (the server adds it to the channel's ``dropped``), so no value
the middleware handed over disappears uncounted. ``dropped_batches`` is the server-wide total.
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
DropFn = Callable[[int], None]
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
        #: Values of dropped batches not yet reported, per ``on_drop`` (under ``_lock``).
        self._drops: dict[DropFn, int] = {}

    def wrap(self, fn: StampedFn, on_drop: DropFn | None = None) -> ValuesCallback:
        """A callback that runs ``fn(values, stamp_ns)`` on the loop thread, from any thread;
        ``on_drop(n)`` (on the loop thread) counts the values of batches dropped on the way."""
        loop_thread = self._loop_thread

        def callback(values: Sequence[Any]) -> None:
            stamp = time.time_ns()
            if threading.get_ident() == loop_thread:
                fn(values, stamp)
            else:
                self._push(fn, values, stamp, on_drop)

        return callback

    def _push(self, fn: StampedFn, values: Sequence[Any], stamp: int,
              on_drop: DropFn | None) -> None:
        with self._lock:
            if len(self._pending) >= self._limit:
                # The deque is full, so a drain is scheduled: it reports this drop.
                self.dropped_batches += 1
                if on_drop is not None:
                    self._drops[on_drop] = self._drops.get(on_drop, 0) + len(values)
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
            drops, self._drops = self._drops, {}
        for fn, values, stamp in items:
            fn(values, stamp)
        for on_drop, count in drops.items():
            on_drop(count)
