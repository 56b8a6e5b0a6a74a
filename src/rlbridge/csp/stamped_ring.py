"""A single-producer ring of ``(stamp, value)`` pairs kept in two preallocated slot lists.

The outgoing channel's ring: storing a tuple per write would allocate on the control
thread's hot path; two parallel slot lists cost two list stores instead. The
synchronisation is :class:`~rlbridge.csp.ring.SpscRing`'s seqlock (read its theory of
operation): the producer stores both slots, then publishes ``_head``; when it overwrites an
unread pair it announces ``_claim`` before the stores. The consumer side is the ring's own
step (``_unread``, copy both slot lists, ``_settle``), which discards what was overwritten
while it copied. A pair is therefore taken whole or not at all: the stamp always belongs to
its value.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from typing import Any, Final

from rlbridge.csp.ring import EMPTY, SpscRing


class _Drain(enum.Enum):
    DRAIN = "DRAIN"


DRAIN: Final = _Drain.DRAIN
"""Returned by :meth:`StampedRing.take_lone` when the ring must be drained instead."""


class StampedRing(SpscRing[Any]):
    """SpscRing plus a parallel stamp slot list; use only the ``*_stamped`` methods."""

    __slots__ = ("_stamps", "taken_stamp")

    def __init__(self, capacity: int) -> None:
        super().__init__(capacity)
        self._stamps: list[int] = [0] * capacity
        #: The stamp of the value :meth:`take_lone` returned last (consumer side only).
        self.taken_stamp = 0

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
        tail, count = self._unread(max_items)
        if not count:
            self._settle(tail, 0)
            return [], []
        cap = self._cap
        first = tail % cap
        stop = first + count
        if stop <= cap:
            stamps = self._stamps[first:stop]
            values = self._slots[first:stop]
        else:
            stamps = self._stamps[first:] + self._stamps[: stop - cap]
            values = self._slots[first:] + self._slots[: stop - cap]
        cut = self._settle(tail, count)
        if cut:  # overwritten while we copied: those pairs may be torn, drop them
            del stamps[:cut]
            del values[:cut]
        return stamps, values

    def take_lone(self) -> Any:
        """Consumer, the send round's common case: the one unread value (its stamp is then
        :attr:`taken_stamp`); :data:`~rlbridge.csp.ring.EMPTY` when none waits; :data:`DRAIN`
        when several wait, or the one was overwritten while it was read (then
        :meth:`drain_stamped` takes what is left).

        The stamp goes to an attribute, not into a returned pair: this runs once per channel
        per round, and a pair would cost the round a tuple (and a boxed int) per value.
        """
        tail = self._tail
        waiting = self._head - tail
        if waiting != 1:
            return EMPTY if not waiting else DRAIN
        i = tail % self._cap
        stamp = self._stamps[i]
        value = self._slots[i]
        if self._settle(tail, 1):
            return DRAIN
        self.taken_stamp = stamp
        return value
