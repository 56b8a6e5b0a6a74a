"""The unbuffered (``buffer_size=0``) channel's hand-over: a lock-based rendezvous.

Split from :mod:`rlbridge.csp.channel` because it shares nothing with the buffered kinds but
the public face: buffered channels are lock-free ring operations; a rendezvous exists to
wait, so one lock and one condition variable are the simplest correct tool. ``Channel``
owns one and forwards its calls here; its counters feed ``Channel.statistics()``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

from rlbridge.csp.statistics import ChannelStatistics
from rlbridge.errors import ChannelClosed, WouldBlock

T = TypeVar("T")


class Rendezvous(Generic[T]):
    """The unbuffered channel: at most one pending offer, handed over under one lock.

    Every state change notifies all waiters, who re-check their own condition: simple to
    reason about, and a spurious wake-up is cheap next to the wait it interrupts.
    """

    __slots__ = ("_closed", "_cond", "_name", "_offer", "_owned", "_seq", "_taken",
                 "dropped", "has_offer", "read_count", "waiting_readers", "waiting_writers",
                 "written")  # fmt: skip

    def __init__(self, name: str) -> None:
        self._name = name
        self._cond = threading.Condition(threading.Lock())
        self._closed = False  # set under the lock: closing and withdrawing are one step
        self._offer: T | None = None
        self.has_offer = False
        self._owned = False  # a blocked writer owns the offer (False: made by try_write)
        self._seq = self._taken = 0  # offers made; sequence number of the last one taken
        self.waiting_readers = self.waiting_writers = 0
        self.written = self.read_count = self.dropped = 0

    def write(self, value: T, timeout: float | None) -> None:
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            if self._closed:
                raise ChannelClosed(self._name)
            self.waiting_writers += 1
            try:
                self._wait_while(lambda: self.has_offer, deadline)  # another writer's turn
                self._seq += 1
                seq = self._seq
                self._offer, self.has_offer, self._owned = value, True, True
                self._cond.notify_all()
                try:
                    self._wait_while(lambda: self._taken < seq, deadline)
                except TimeoutError:  # not taken: withdraw (close withdraws by itself)
                    self._offer, self.has_offer = None, False
                    self._cond.notify_all()
                    raise
                self.written += 1
            finally:
                self.waiting_writers -= 1

    def try_write(self, value: T) -> None:
        with self._cond:
            if self._closed:
                raise ChannelClosed(self._name)
            if self.has_offer or self.waiting_readers == 0:
                raise WouldBlock(self._name, "try_write")
            # A blocked reader re-checks for an offer before it gives up: it takes this.
            self._seq += 1
            self._offer, self.has_offer, self._owned = value, True, False
            self.written += 1
            self._cond.notify_all()

    def read(self, timeout: float | None, on_block: Callable[[], None]) -> T:
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            self.waiting_readers += 1
            try:
                if not self.has_offer and not self._closed:
                    on_block()
                self._wait_while(lambda: not self.has_offer, deadline)
                return self._take()
            finally:
                self.waiting_readers -= 1

    def try_read(self) -> T:
        with self._cond:
            if self.has_offer:
                return self._take()
            if self._closed:
                raise ChannelClosed(self._name)
            raise WouldBlock(self._name, "try_read")

    def close(self) -> None:
        with self._cond:
            self._closed = True
            if self.has_offer and not self._owned:
                self.dropped += 1  # try_write's value: its writer has already returned
            self._offer, self.has_offer = None, False
            self._cond.notify_all()

    def statistics(self, closed: bool, hrt_blocking_reads: int) -> ChannelStatistics:
        with self._cond:
            return ChannelStatistics(
                buffered=int(self.has_offer and not self._owned),
                overwritten=0,
                dropped=self.dropped,
                written=self.written,
                read=self.read_count,
                waiting_readers=self.waiting_readers,
                waiting_writers=self.waiting_writers,
                closed=closed,
                hrt_blocking_reads=hrt_blocking_reads,
            )

    def _take(self) -> T:
        value: T = self._offer  # type: ignore[assignment]  # has_offer: it is a T
        self._offer, self.has_offer = None, False
        self._taken = self._seq
        self.read_count += 1
        self._cond.notify_all()
        return value

    def _wait_while(self, busy: Callable[[], bool], deadline: float | None) -> None:
        """Wait (lock held) while ``busy()``; raise on close or once the deadline passed."""
        while busy():
            if self._closed:
                raise ChannelClosed(self._name)
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                raise TimeoutError(f"rendezvous on channel {self._name!r} timed out")
            self._cond.wait(remaining)
