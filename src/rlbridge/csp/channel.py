"""CSP channels with the semantics of the thesis (section 3.4.1), in a Go/trio vocabulary.

Three kinds, chosen by the constructor:

* ``Channel()`` (``buffer_size=0``): a blocking rendezvous. ``write`` returns only once
  a reader has taken the value; ``read`` waits for a writer. Any number of threads on
  either end; lock-based, because waiting is its purpose.
* ``Channel(n)`` (``blocking=True``): the writer never blocks, it overwrites the oldest
  value when the buffer is full (counted in ``overwritten``); the reader waits when the
  buffer is empty.
* ``Channel(n, blocking=False, initial=...)``: neither side blocks; a reader with nothing
  new gets the most recent value again (or ``initial``; with neither, :class:`NoValueYet`).

Buffered channels are the hard-real-time path. They are one-to-one (one writer thread and
one reader thread at a time, as in CSP): writes and reads are a lock-free :class:`SpscRing`
operation, with no lock, no system call and no allocation in steady state. Two threads
using the same end at the same moment would lose values silently, so each end carries a
one-element token list: ``list.pop``/``list.append`` are atomic, and an overlapping second
user finds the list empty and gets :class:`ChannelMisuseError` (about 60 ns per call).

Waking a blocked reader is the only place where a write may make a system call. A reader
that finds the buffer empty registers in a :class:`Doorbell` (under its lock) and
re-checks the buffer before sleeping; the writer stores the value, then reads the
doorbell's ``waiting`` count and rings (lock + futex wake) only when it is non-zero. Store
then check on one side and register then check on the other cannot both miss under
sequential consistency, which the GIL provides. ``threading.Condition.notify`` alone would
take a lock on every write, even with nobody waiting. Non-blocking channels never have a
waiting reader, so they never ring. Several channels may share a doorbell so that one
consumer (the SDK's send thread) can sleep until any of them is written.

How a blocking read waits is its ``read_idle`` strategy (:mod:`rlbridge.csp.idle`; the
SDK's incoming channels take the receive thread's): ``PARK`` sleeps on the doorbell at once; a
spinning strategy first polls the buffer, giving up the CPU and the GIL between polls, and
is not registered in the doorbell meanwhile, so the writer finds nobody to wake.
"""

from __future__ import annotations

import enum
import os
import time
import warnings
from collections.abc import Sequence
from types import TracebackType
from typing import Final, Generic, TypeVar

from mypy_extensions import mypyc_attr

from rlbridge.csp.doorbell import Doorbell
from rlbridge.csp.idle import PARK, IdleStrategy
from rlbridge.csp.process import current_process
from rlbridge.csp.rendezvous import Rendezvous
from rlbridge.csp.ring import EMPTY, SpscRing
from rlbridge.csp.statistics import ChannelStatistics
from rlbridge.errors import (
    ChannelClosed,
    ChannelMisuseError,
    NoValueYet,
    RealTimeWarning,
    WouldBlock,
)

__all__ = ["Channel", "Doorbell"]

T = TypeVar("T")


class _Missing(enum.Enum):
    MISSING = "MISSING"


_MISSING: Final = _Missing.MISSING
_yield_cpu = os.sched_yield


# Compiled by mypyc (rlbridge/_compiled.py); ServiceRequests (csp/services.py) subclasses it.
@mypyc_attr(allow_interpreted_subclasses=True)
class Channel(Generic[T]):
    """A CSP channel; see the module docstring for the three kinds."""

    __slots__ = ("_bell", "_blocking", "_closed", "_hrt_blocking_reads", "_hrt_warned",
                 "_initial", "_name", "_read_token", "_ring", "_rv", "_stale_reads",
                 "_waiting_readers", "_write_token", "read_idle")  # fmt: skip

    def __init__(
        self,
        buffer_size: int = 0,
        *,
        blocking: bool = True,
        initial: T | _Missing = _MISSING,
        name: str | None = None,
        doorbell: Doorbell | None = None,
    ) -> None:
        if buffer_size < 0:
            raise ValueError(f"buffer_size must be >= 0, got {buffer_size}")
        if buffer_size == 0 and not blocking:
            raise ValueError("a non-blocking channel needs buffer_size >= 1 (thesis 3.4.1)")
        if initial is not _MISSING and blocking:
            raise ValueError("initial= only applies to non-blocking channels")
        self._name: Final = name if name is not None else f"channel@{id(self):#x}"
        self._blocking: Final = blocking
        self._initial: Final = initial
        self._bell: Final = doorbell if doorbell is not None else Doorbell()
        self._ring: Final[SpscRing[T]] = SpscRing(max(buffer_size, 1))
        self._rv: Final = Rendezvous[T](self._name) if buffer_size == 0 else None
        self._closed = False
        self._write_token: Final[list[None]] = [None]
        self._read_token: Final[list[None]] = [None]
        self._waiting_readers = self._stale_reads = self._hrt_blocking_reads = 0
        self._hrt_warned = False
        #: How a blocking read waits for a value (:mod:`rlbridge.csp.idle`): ``PARK`` blocks
        #: on the doorbell at once; a spinning strategy polls the buffer first, yielding the
        #: CPU and the GIL between polls, so that a value written meanwhile costs no wake-up.
        self.read_idle: IdleStrategy = PARK

    @property
    def name(self) -> str:
        """The name used in errors, warnings and statistics."""
        return self._name

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    def write(self, value: T, timeout: float | None = None) -> None:
        """Write ``value``; blocks only on a rendezvous channel (until a reader takes it).

        Raises :class:`ChannelClosed` after ``close()``, :class:`TimeoutError` when a
        rendezvous write is not taken within ``timeout`` seconds (the value is withdrawn).
        """
        rv = self._rv
        if rv is not None:
            rv.write(value, timeout)
            return
        if self._closed:
            raise ChannelClosed(self._name)
        token = self._write_token
        try:
            token.pop()
        except IndexError:
            raise ChannelMisuseError(self._name, "writer") from None
        try:
            self._ring.push_overwrite(value)
        finally:
            token.append(None)
        bell = self._bell
        if bell.waiting:
            bell.ring()

    def try_write(self, value: T) -> None:
        """Write without waiting: a rendezvous needs a reader already blocked in ``read``.

        Raises :class:`WouldBlock` when that reader is missing; buffered channels always
        accept, so for them this is :meth:`write`.
        """
        if self._rv is not None:
            self._rv.try_write(value)
        else:
            self.write(value)

    def deliver_many(self, values: Sequence[T]) -> None:
        """Bulk write for a feeding thread (the SDK's receive thread); one wake-up per batch.

        Same overwrite policy as :meth:`write`; on a rendezvous each value is a write.
        """
        if self._rv is not None:
            for value in values:
                self._rv.write(value, None)
            return
        if self._closed:
            raise ChannelClosed(self._name)
        token = self._claim(self._write_token, "writer")
        try:
            self._ring.push_many(values, overwrite=True)
        finally:
            token.append(None)
        if self._bell.waiting:
            self._bell.ring()

    def read(self, timeout: float | None = None) -> T:
        """Read one value, waiting on rendezvous and blocking buffered channels.

        Raises :class:`TimeoutError` after ``timeout`` seconds, :class:`ChannelClosed`
        once the channel is closed and drained, and :class:`NoValueYet` from a
        non-blocking channel that never had a value.
        """
        rv = self._rv
        if rv is not None:
            return rv.read(timeout, self._note_blocking_read)
        token = self._read_token
        try:
            token.pop()
        except IndexError:
            raise ChannelMisuseError(self._name, "reader") from None
        try:
            value = self._ring.pop()
            if value is not EMPTY:
                return value
            if not self._blocking:
                return self._latest()
            return self._wait_and_pop(timeout)
        finally:
            token.append(None)

    def try_read(self) -> T:
        """Read without waiting; raises :class:`WouldBlock` when a wait would be needed."""
        if self._rv is not None:
            return self._rv.try_read()
        try:
            return self.read(timeout=0.0)
        except TimeoutError:
            raise WouldBlock(self._name, "try_read") from None

    def read_many(self, max_items: int | None = None) -> list[T]:
        """Take every new value (up to ``max_items``) without waiting, for batch consumers.

        Returns ``[]`` when nothing is new (a non-blocking channel does not repeat its
        latest value here); raises :class:`ChannelClosed` once closed and drained.
        """
        if self._rv is not None:
            try:
                return [self._rv.try_read()]
            except WouldBlock:
                return []
        token = self._claim(self._read_token, "reader")
        try:
            values = self._ring.pop_many(max_items)
        finally:
            token.append(None)
        if not values and self._closed:
            raise ChannelClosed(self._name)
        return values

    def close(self) -> None:
        """Refuse further writes and wake every blocked party with :class:`ChannelClosed`.

        Buffered values stay readable; a rendezvous offer made by ``try_write`` that no
        reader took yet is discarded and counted in ``dropped``.
        """
        self._closed = True
        if self._rv is not None:
            self._rv.close()
        self._bell.ring()

    def __enter__(self) -> Channel[T]:
        return self

    def __exit__(self, et: type[BaseException] | None, e: BaseException | None,
                 tb: TracebackType | None) -> None:
        """Leaving a ``with`` block closes the channel (:meth:`close`)."""
        self.close()

    def statistics(self) -> ChannelStatistics:
        """Return a snapshot of the counters (taken without stopping either side)."""
        if self._rv is not None:
            return self._rv.statistics(self._closed, self._hrt_blocking_reads)
        ring = self._ring
        return ChannelStatistics(
            buffered=len(ring),
            overwritten=ring.overwritten,
            dropped=ring.dropped,
            written=ring.written,
            read=ring.popped,
            waiting_readers=self._waiting_readers,
            waiting_writers=0,
            closed=self._closed,
            stale_reads=self._stale_reads,
            hrt_blocking_reads=self._hrt_blocking_reads,
        )

    def __len__(self) -> int:
        """Values ready to read now (for a consumer's doorbell predicate); lock-free."""
        return len(self._ring) if self._rv is None else int(self._rv.has_offer)

    def __repr__(self) -> str:
        kind = "rendezvous" if self._rv else ("blocking" if self._blocking else "non-blocking")
        return f"<Channel {self._name!r} {kind} capacity={self._ring.capacity}>"

    def _claim(self, token: list[None], end: str) -> list[None]:
        """Take an end's token (batch paths; the per-value paths inline this)."""
        try:
            token.pop()
        except IndexError:
            raise ChannelMisuseError(self._name, end) from None
        return token

    def _latest(self) -> T:
        """Non-blocking read with nothing new: repeat the most recent value.

        A value written between the empty ``pop`` and ``peek_latest`` is returned here as
        the latest and again by the next read as new: a repeat, which non-blocking readers
        must tolerate anyway, never a loss.
        """
        if self._closed:
            raise ChannelClosed(self._name)
        value = self._ring.peek_latest()
        if value is EMPTY:
            if self._initial is _MISSING:
                raise NoValueYet(self._name)
            value = self._initial
        self._stale_reads += 1
        return value

    def _readable(self) -> bool:
        return len(self._ring) > 0 or self._closed

    def _poll_readable(self) -> bool:
        """A spinning read's poll: the buffer, else a ``sched_yield`` (lets the GIL go).

        The writer is often the same process's receive thread, which needs the GIL to deliver:
        a poll that held it would delay the very value it waits for.
        """
        if len(self._ring) > 0 or self._closed:
            return True
        _yield_cpu()
        return False

    def _park(self, timeout: float | None) -> bool:
        return self._bell.wait_for(self._readable, timeout)

    def _wait_and_pop(self, timeout: float | None) -> T:
        """Slow path of a blocking buffered read: the buffer was empty."""
        deadline = None if timeout is None else time.monotonic() + timeout
        noted = False
        while True:
            if self._closed:
                value = self._ring.pop()  # a write may have landed just before close
                if value is EMPTY:
                    raise ChannelClosed(self._name)
                return value
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                raise TimeoutError(f"read on channel {self._name!r} timed out after {timeout}s")
            if not noted:
                noted = True
                self._note_blocking_read()
            self._waiting_readers += 1
            try:
                idle = self.read_idle
                if idle is PARK:
                    self._bell.wait_for(self._readable, remaining)
                else:
                    idle.idle(self._poll_readable, self._park, remaining)
            finally:
                self._waiting_readers -= 1
            value = self._ring.pop()
            if value is not EMPTY:
                return value

    def _note_blocking_read(self) -> None:
        """Count, and warn once about, a hard-real-time process about to wait here.

        That is the thesis's "naive receive" (section 5.3.1): the HRT loop becomes
        synchronised with the arrival of messages and its jitter grows to one period.
        """
        info = current_process()
        if info is None or not info.hrt:
            return
        self._hrt_blocking_reads += 1
        if not self._hrt_warned:
            self._hrt_warned = True
            warnings.warn(
                RealTimeWarning(
                    f"hard-real-time process {info.name!r} blocked reading channel "
                    f"{self._name!r}; read HRT inputs from a non-blocking channel, or move "
                    "the blocking read to a lower-priority process (thesis 5.2.1)"
                ),
                stacklevel=4,  # _note <- _wait_and_pop or Rendezvous.read <- read <- caller
            )
