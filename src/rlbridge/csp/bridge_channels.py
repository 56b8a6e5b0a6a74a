"""Bridge channels: CSP channels whose other end is a topic on the middleware.

An :class:`IncomingChannel` *is* a buffered :class:`~rlbridge.csp.channel.Channel`; the receive
thread is its writer (one bulk ``deliver_many`` per packet) and control code its reader, with the
blocking or non-blocking semantics of thesis 3.4.1. Before values enter it, a
:class:`~rlbridge.wire.sequence.SequenceTracker` drops duplicates and overtaken values (UDP,
redundant datagrams) and counts gaps as lost.

An :class:`OutgoingChannel` is the writer end only: ``write`` stamps the value and stores it in
a lock-free ring; the send thread is its reader. With ``immediate=True`` (``through_buffer``
off) a write also rings the send thread's doorbell, which costs a futex wake *only* when the send
thread sleeps; with ``through_buffer`` on, a write makes no system call at all and the value
leaves on ``Bridge.send()`` or the next send-loop tick.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from rlbridge.csp.channel import _MISSING, Channel, ChannelStatistics, Doorbell, _Missing
from rlbridge.csp.errors import ChannelClosed
from rlbridge.csp.ring import SpscRing
from rlbridge.wire.sequence import SequenceTracker


class IncomingChannel(Channel[Any]):
    """Middleware -> control code. Read it like any buffered channel."""

    __slots__ = ("_tracker", "channel_id", "field", "last_stamp_ns", "msg_type", "topic",
                 "transport")

    def __init__(self, channel_id: int, topic: str, msg_type: str, field: str | None, *,
                 transport: str, blocking: bool, buffer_size: int,
                 initial: Any | _Missing = _MISSING) -> None:
        super().__init__(buffer_size, blocking=blocking, initial=initial,
                         name=f"{topic} [{msg_type} {field or '<message>'}] in")
        self.channel_id = channel_id
        self.topic = topic
        self.msg_type = msg_type
        self.field = field
        self.transport = transport
        self.last_stamp_ns = 0
        self._tracker = SequenceTracker()

    def restart_sequence(self) -> None:
        """The channel was bound again (reconnect): the server numbers from 0 again."""
        self._tracker.restart()

    def deliver(self, first_seq: int, stamps: list[int], values: list[Any]) -> None:
        """Called by the receive thread with one packet's values."""
        start = self._tracker.accept_run(first_seq, len(values))
        if start >= len(values) or self.closed:
            return
        self.last_stamp_ns = stamps[-1]
        self.deliver_many(values[start:] if start else values)

    @property
    def age_ns(self) -> int:
        """Nanoseconds since the server sent the newest value (-1 before the first one)."""
        return time.time_ns() - self.last_stamp_ns if self.last_stamp_ns else -1

    @property
    def lost(self) -> int:
        """Values the server sent that never arrived (sequence gaps)."""
        return self._tracker.lost

    @property
    def duplicates(self) -> int:
        """Values that arrived twice (redundant UDP) or out of order, and were dropped."""
        return self._tracker.duplicates + self._tracker.stale


class OutgoingChannel:
    """Control code -> middleware. ``write`` never blocks and never touches a socket."""

    __slots__ = ("_bell", "_closed", "_next_seq", "_ring", "channel_id", "field", "immediate",
                 "msg_type", "topic", "transport")

    def __init__(self, channel_id: int, topic: str, msg_type: str, field: str | None, *,
                 transport: str, immediate: bool, buffer_size: int, doorbell: Doorbell) -> None:
        if buffer_size < 1:
            raise ValueError(f"an outgoing channel needs buffer_size >= 1, got {buffer_size}")
        self.channel_id = channel_id
        self.topic = topic
        self.msg_type = msg_type
        self.field = field
        self.transport = transport
        self.immediate = immediate
        self._ring: SpscRing[tuple[int, Any]] = SpscRing(buffer_size)
        self._bell = doorbell
        self._next_seq = 0
        self._closed = False

    def write(self, value: Any) -> None:
        """Queue one value for the send thread; a full buffer drops its oldest value (counted)."""
        if self._closed:
            raise ChannelClosed(self.topic)
        self._ring.push_overwrite((time.time_ns(), value))
        if self.immediate:
            bell = self._bell
            if bell.waiting:
                bell.ring()

    def write_many(self, values: Sequence[Any]) -> None:
        """Queue a batch (one stamp for all): the cheapest way to move many values."""
        if self._closed:
            raise ChannelClosed(self.topic)
        stamp = time.time_ns()
        self._ring.push_many([(stamp, v) for v in values], overwrite=True)
        if self.immediate:
            bell = self._bell
            if bell.waiting:
                bell.ring()

    def pending(self) -> int:
        """Values written and not yet taken by the send thread (a snapshot, for monitors)."""
        return len(self._ring)

    def take(self) -> tuple[int, list[int], list[object]]:
        """Send thread: everything waiting, numbered from the channel's next sequence number."""
        items = self._ring.pop_many()
        first = self._next_seq
        self._next_seq = first + len(items)
        return first, [s for s, _ in items], [v for _, v in items]

    def statistics(self) -> ChannelStatistics:
        """Counters as for a :class:`Channel`; ``overwritten`` is what a full buffer dropped."""
        ring = self._ring
        return ChannelStatistics(buffered=len(ring), overwritten=ring.overwritten, dropped=0,
                                 written=ring.written, read=ring.popped, waiting_readers=0,
                                 waiting_writers=0, closed=self._closed)

    @property
    def closed(self) -> bool:
        """True after :meth:`close` (``Bridge.unsubscribe`` or ``Bridge.close``)."""
        return self._closed

    def close(self) -> None:
        """Refuse further writes (``ChannelClosed``); ``Bridge.unsubscribe`` also unbinds it."""
        self._closed = True
