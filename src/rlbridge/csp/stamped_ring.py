"""A single-producer ring of ``(stamp, value)`` pairs kept in two preallocated slot lists.

The outgoing channel's ring: storing a tuple per write would allocate on the control
thread's hot path; two parallel slot lists cost two list stores instead. The
synchronisation is :class:`~rlbridge.csp.ring.SpscRing`'s seqlock (read its theory of
operation): the producer stores both slots, then publishes ``_head``; when it overwrites an
unread pair it announces ``_claim`` before the stores, and the consumer, after copying,
discards everything below ``_claim - capacity`` as overwritten. A pair is therefore taken
whole or not at all: the stamp always belongs to its value.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from rlbridge.csp.ring import SpscRing


class StampedRing(SpscRing[Any]):
    """SpscRing plus a parallel stamp slot list; use only the ``*_stamped`` methods."""

    __slots__ = ("_stamps",)

    def __init__(self, capacity: int) -> None:
        super().__init__(capacity)
        self._stamps: list[int] = [0] * capacity

    def push_stamped(self, stamp: int, value: Any) -> bool:
        """Store one pair, displacing the oldest unread pair when full (returns ``full``)."""
        head = self._head
        cap = self._cap
        nxt = head + 1
        full = head - self._tail >= cap
        if full:
            self._claim = nxt
        i = head % cap
        self._stamps[i] = stamp
        self._slots[i] = value
        self._head = nxt
        return full

    def push_many_stamped(self, stamp: int, values: Sequence[Any]) -> None:
        """Store a batch sharing one stamp (overwrite policy as ``push_many``)."""
        count = len(values)
        if count == 0:
            return
        head = self._head
        cap = self._cap
        end = head + count
        if end - self._tail > cap:
            self._claim = end
        stamps, slots = self._stamps, self._slots
        for i in range(max(0, count - cap), count):
            j = (head + i) % cap
            stamps[j] = stamp
            slots[j] = values[i]
        self._head = end

    def drain_stamped(self, max_items: int | None = None) -> tuple[list[int], list[Any]]:
        """Consumer: the unread pairs (at most ``max_items``), oldest first, as
        ``(stamps, values)``; the rest stay for the next call (rate limit, credit)."""
        cap = self._cap
        tail = self._tail
        head = self._head
        lost = head - cap - tail
        if lost > 0:
            self._skipped += lost
            tail += lost
        count = head - tail
        if max_items is not None:
            count = min(count, max_items)
        if count <= 0:
            if lost > 0:
                self._tail = tail
            return [], []
        first = tail % cap
        stop = first + count
        if stop <= cap:
            stamps = self._stamps[first:stop]
            values = self._slots[first:stop]
        else:
            stamps = self._stamps[first:] + self._stamps[: stop - cap]
            values = self._slots[first:] + self._slots[: stop - cap]
        lost = self._claim - cap - tail
        if lost > 0:  # overwritten while we copied: those pairs may be torn, drop them
            cut = min(lost, count)
            del stamps[:cut]
            del values[:cut]
            self._skipped += lost
            self._tail = tail + max(lost, count)
            return stamps, values
        self._tail = tail + count
        return stamps, values
