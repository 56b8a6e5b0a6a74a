"""Lock-free bounded ring buffers between hard-real-time threads and I/O threads.

Theory of operation
-------------------
An :class:`SpscRing` is a preallocated Python list of ``capacity`` slots and three
monotonically increasing sequence counters:

* ``_head``  (written only by the producer): sequence number of the next value to store;
* ``_claim`` (written only by the producer): ``s + 1`` once the producer has *started*
  to overwrite the slot of an unread value for sequence ``s`` (only set when full);
* ``_tail``  (written only by the consumer): sequence number of the next value to take.

Value ``s`` lives in slot ``s % capacity``. Producer and consumer never write the same
variable, so no lock is needed: the producer stores the slot and *then* publishes
``_head``; the consumer reads ``_head``, then the slot, then stores ``_tail``.

Overwriting (``push_overwrite``) is the hard part: when the ring is full the producer
reuses the slot of the oldest unread value while the consumer may be reading that very
slot. The producer therefore announces ``_claim = s + 1`` *before* storing, and the
consumer re-reads ``_claim`` *after* reading a slot (a seqlock): value ``t`` is valid
only if ``_claim <= t + capacity``. Otherwise every sequence below
``_claim - capacity`` is lost, the consumer skips to there, counts the skipped values
in ``overwritten`` and retries. The consumer therefore sees a strictly increasing
subsequence of what was written, never a duplicate or a reordering. Loss is decided
and counted by the consumer, so the counters are exact: once both sides are quiet,
``written == popped + overwritten + len(ring)`` (values refused by a full ``push`` were
never written; they are counted in ``dropped``).
``push_overwrite`` returns ``True`` when the ring looked full, which means "the oldest
unread value was displaced" except in one race: if the consumer was in the middle of
taking exactly that value, it may still get it. Trust the counters, not the flag.

What this relies on
-------------------
On a GIL build of CPython (3.11, 3.12, 3.13 default) one bytecode-level operation that
runs no Python code is atomic and all threads see operations in one global order
(sequential consistency, because every switch goes through the GIL's mutex). The ring
uses only such operations: ``list[i]`` load/store and attribute load/store on a
``__slots__`` instance. Decrementing the replaced slot value may run a ``__del__``,
but only after the store completed. (CPython 3.11 in fact hands the GIL over only at
function entries, backward jumps and calls, so a switch *inside* these methods needs a
``__del__``, a trace function or a free-threaded build; the design does not rely on
that implementation detail, and the tests force switches at every line.)

On a free-threaded build (3.13t) each of those operations is still atomic (PEP 703
keeps list items and attributes thread-safe), but CPython documents no memory model
for ordering operations on *different* objects; the seqlock needs "slot then head"
and "slot then claim" to be observed in program order. CPython implements them with
atomics/per-object locks that give that order on x86 and, as far as the implementation
goes, on ARM, but it is not promised: the stress tests in ``tests/csp/test_ring.py``
are the check to run on such a build before relying on it.

Cost and allocation
-------------------
Every operation is O(1): no lock, no system call. The counters are Python ints; above
256 CPython allocates a new int per increment and frees the old one (pymalloc free
list, no system call), so the *net* allocation in steady state is zero, which is what
tracemalloc measures and what the tests check. The ring keeps a reference to the last
``capacity`` values: a slot is released only when it is reused, because the consumer
may not clear a slot the producer might already be refilling.

Several writers
---------------
A lock-free multi-producer ring is possible under the GIL (``itertools.count`` is an
atomic ticket dispenser) but a producer that claims a ticket on a full ring leaves a
hole the consumer must detect and skip. :class:`MpscRing` avoids this entirely: every
producer thread gets its own SPSC lane, registered once under a lock, and the single
consumer (the send thread) drains all lanes. Writers never contend; order is FIFO per
producer, and there is no order between producers.
"""

from __future__ import annotations

import enum
import threading
from collections.abc import Sequence
from typing import Final, Generic, Literal, TypeAlias, TypeVar

T = TypeVar("T")


class _Empty(enum.Enum):
    EMPTY = "EMPTY"


EMPTY: Final = _Empty.EMPTY
"""Returned by ``pop`` and ``peek_latest`` when there is nothing to return."""

Empty: TypeAlias = Literal[_Empty.EMPTY]


class SpscRing(Generic[T]):
    """Bounded lock-free ring for exactly one producer thread and one consumer thread.

    Producer side: :meth:`push`, :meth:`push_overwrite`, :meth:`push_many`.
    Consumer side: :meth:`pop`, :meth:`drain_into`, :meth:`pop_many`.
    Any thread: :meth:`peek_latest`, ``len()`` and the counters (snapshots).
    """

    __slots__ = ("_cap", "_claim", "_dropped", "_head", "_skipped", "_slots", "_tail")

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"ring capacity must be >= 1, got {capacity}")
        self._cap: Final = capacity
        self._slots: list[T | None] = [None] * capacity
        self._head = 0
        self._claim = 0
        self._tail = 0
        self._skipped = 0
        self._dropped = 0

    # -- producer ---------------------------------------------------------------------

    def push(self, value: T) -> bool:
        """Store ``value``; return ``False`` (and count it in ``dropped``) when full."""
        head = self._head
        if head - self._tail >= self._cap:
            self._dropped += 1
            return False
        self._slots[head % self._cap] = value
        self._head = head + 1
        return True

    def push_overwrite(self, value: T) -> bool:
        """Always store ``value``; when full, displace the oldest unread value.

        Returns ``True`` when the ring looked full (see the module notes for the one
        race in which the consumer still gets the displaced value).
        """
        head = self._head
        cap = self._cap
        nxt = head + 1
        # A stale _tail is smaller than the real one, so "full" can only be a false
        # alarm (a harmless extra claim), never a missed overwrite.
        full = head - self._tail >= cap
        if full:
            self._claim = nxt  # announce before the store: the seqlock
        self._slots[head % cap] = value
        self._head = nxt
        return full

    def push_many(self, values: Sequence[T], *, overwrite: bool = False) -> int:
        """Store a batch; return how many values were accepted.

        Without ``overwrite`` the values that do not fit are refused and counted in
        ``dropped``. With ``overwrite`` all are accepted; if the batch is longer than
        the ring only its last ``capacity`` values are stored and the rest are counted
        as overwritten by the consumer, exactly as if pushed one by one.
        """
        count = len(values)
        if count == 0:
            return 0
        head = self._head
        cap = self._cap
        slots = self._slots
        if not overwrite:
            accept = min(count, cap - (head - self._tail))
            accept = max(accept, 0)
            for i in range(accept):
                slots[(head + i) % cap] = values[i]
            self._head = head + accept
            if accept < count:
                self._dropped += count - accept
            return accept
        end = head + count
        if end - self._tail > cap:
            self._claim = end  # covers every sequence up to end - 1
        if count > cap:  # only the last ``cap`` values can be stored
            values = values[count - cap :]
        stored = len(values)
        # One or two slice stores (C level, no per-value bytecode); each slice on the right
        # has exactly the length of the one it replaces, so the slot list never resizes.
        first = (end - stored) % cap
        stop = first + stored
        if stop <= cap:
            slots[first:stop] = values
        else:
            split = cap - first
            slots[first:] = values[:split]
            slots[: stop - cap] = values[split:]
        self._head = end
        return count

    # -- consumer ---------------------------------------------------------------------
    # Every way of taking values (here, and StampedRing's pairs) is the same seqlock step:
    # _unread (skip what the producer lapped), copy the slots, _settle (the claim check,
    # then the tail). The step exists once, in these two methods.

    def _unread(self, max_items: int | None) -> tuple[int, int]:
        """Consumer, before copying: ``(sequence of the oldest value still stored, how many
        of them to copy)``; what the producer lapped is counted as overwritten."""
        tail = self._tail
        head = self._head
        lost = head - self._cap - tail
        if lost > 0:  # the producer lapped us: skip what it overwrote
            self._skipped += lost
            tail += lost
        count = head - tail
        if max_items is not None and count > max_items:
            count = max(max_items, 0)
        return tail, count

    def _settle(self, tail: int, count: int) -> int:
        """Consumer, after copying ``count`` slots from sequence ``tail``: the seqlock check.

        Returns how many of the copied values, from the first, the producer was overwriting
        meanwhile (the caller discards them: they may be torn); the tail moves past all of
        them, and the discarded ones are counted as overwritten.
        """
        lost = self._claim - self._cap - tail
        if lost <= 0:
            self._tail = tail + count
            return 0
        self._skipped += lost
        self._tail = tail + max(lost, count)
        return min(lost, count)

    def pop(self) -> T | Empty:
        """Take the oldest unread value, or return :data:`EMPTY`."""
        while True:
            tail, count = self._unread(1)
            if not count:
                return EMPTY
            value = self._slots[tail % self._cap]
            if not self._settle(tail, 1):
                return value  # type: ignore[return-value]  # slot holds a T once written
            # The slot was being overwritten while we read it: skipped, try the next one.

    def drain_into(self, out: list[T], max_items: int | None = None) -> int:
        """Append up to ``max_items`` unread values to ``out``; return how many."""
        tail, count = self._unread(max_items)
        start = len(out)
        if count:
            cap = self._cap
            slots = self._slots
            first = tail % cap
            stop = first + count
            if stop <= cap:
                out.extend(slots[first:stop])  # type: ignore[arg-type]
            else:  # wraps around the end of the slot list
                out.extend(slots[first:])  # type: ignore[arg-type]
                out.extend(slots[: stop - cap])  # type: ignore[arg-type]
        cut = self._settle(tail, count)
        if cut:
            del out[start : start + cut]
        return count - cut

    def pop_many(self, max_items: int | None = None) -> list[T]:
        """Return up to ``max_items`` unread values as a new list (batch consumers)."""
        out: list[T] = []
        self.drain_into(out, max_items)
        return out

    # -- any thread -------------------------------------------------------------------

    def peek_latest(self) -> T | Empty:
        """Return the most recently pushed value (read or not), or :data:`EMPTY`."""
        head = self._head
        if head == 0:
            return EMPTY
        return self._slots[(head - 1) % self._cap]  # type: ignore[return-value]

    def __len__(self) -> int:
        return max(0, min(self._head - self._tail, self._cap))

    @property
    def capacity(self) -> int:
        """Number of slots."""
        return self._cap

    @property
    def written(self) -> int:
        """Values accepted by the producer so far (including later overwritten ones)."""
        return self._head

    @property
    def popped(self) -> int:
        """Values handed to the consumer so far."""
        return self._tail - self._skipped

    @property
    def overwritten(self) -> int:
        """Values displaced before the consumer took them (skipped + still pending)."""
        return self._skipped + max(0, self._head - self._tail - self._cap)

    @property
    def dropped(self) -> int:
        """Values refused by :meth:`push`/:meth:`push_many` because the ring was full."""
        return self._dropped


class MpscRing(Generic[T]):
    """Fan-in of per-producer :class:`SpscRing` lanes drained by one consumer thread.

    Each producer thread gets its own lane on its first push (one short lock, once per
    thread); afterwards a push is a thread-local lookup plus a lock-free SPSC push.
    Lanes of producer threads that have ended stay (their values are still drained);
    the number of lanes is bounded by the number of threads that ever pushed.
    """

    __slots__ = ("_lane_capacity", "_lanes", "_local", "_next", "_overwrite", "_register_lock")

    def __init__(self, lane_capacity: int, *, overwrite: bool = False) -> None:
        if lane_capacity < 1:
            raise ValueError(f"lane capacity must be >= 1, got {lane_capacity}")
        self._lane_capacity: Final = lane_capacity
        self._overwrite: Final = overwrite
        self._lanes: tuple[SpscRing[T], ...] = ()
        self._local = threading.local()
        self._register_lock = threading.Lock()
        self._next = 0

    def lane(self) -> SpscRing[T]:
        """The calling thread's lane (created on first use)."""
        try:
            lane: SpscRing[T] = self._local.lane
        except AttributeError:
            lane = SpscRing(self._lane_capacity)
            with self._register_lock:
                # Copy-on-write: the consumer iterates a snapshot tuple, lock-free.
                self._lanes = (*self._lanes, lane)
            self._local.lane = lane
        return lane

    def push(self, value: T) -> bool:
        """Push into the calling thread's lane (overwrite policy fixed at construction)."""
        if self._overwrite:
            self.lane().push_overwrite(value)
            return True
        return self.lane().push(value)

    def drain_into(self, out: list[T], max_items: int | None = None) -> int:
        """Consumer: append up to ``max_items`` values from all lanes to ``out``.

        The starting lane rotates so that a bounded drain does not starve any lane.
        """
        lanes = self._lanes
        if not lanes:
            return 0
        total = 0
        first = self._next % len(lanes)
        for i in range(len(lanes)):
            budget = None if max_items is None else max_items - total
            if budget == 0:
                break
            total += lanes[(first + i) % len(lanes)].drain_into(out, budget)
        self._next = first + 1
        return total

    def pop_many(self, max_items: int | None = None) -> list[T]:
        """Consumer: return up to ``max_items`` values from all lanes as a new list."""
        out: list[T] = []
        self.drain_into(out, max_items)
        return out

    def __len__(self) -> int:
        return sum(len(lane) for lane in self._lanes)

    @property
    def lanes(self) -> int:
        """Number of producer lanes registered so far."""
        return len(self._lanes)

    @property
    def written(self) -> int:
        """Values accepted over all lanes."""
        return sum(lane.written for lane in self._lanes)

    @property
    def popped(self) -> int:
        """Values handed to the consumer over all lanes."""
        return sum(lane.popped for lane in self._lanes)

    @property
    def overwritten(self) -> int:
        """Values displaced before being drained, over all lanes."""
        return sum(lane.overwritten for lane in self._lanes)

    @property
    def dropped(self) -> int:
        """Values refused because their lane was full, over all lanes."""
        return sum(lane.dropped for lane in self._lanes)
