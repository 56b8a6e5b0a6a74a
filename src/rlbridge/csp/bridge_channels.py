"""Bridge channels: CSP channels whose other end is a topic on the middleware.

An :class:`IncomingChannel` *is* a buffered :class:`~rlbridge.csp.channel.Channel`; the receive
thread is its writer (one bulk ``deliver_many`` per packet) and control code its reader, with the
blocking or non-blocking semantics of thesis 3.4.1. Before values enter it, a
:class:`~rlbridge.wire.sequence.SequenceTracker` drops duplicates and overtaken values (UDP,
redundant datagrams) and counts gaps as lost; then the channel's policies apply
(docs/policies.md): ``max_age_ms`` drops values older than the limit (``expired``), and
``latest`` keeps only the newest value of what arrived together (``overtaken``), so a reader
behind a TCP retransmission gets the newest set-point, not a burst of stale ones. The ring
holds ``(stamp, value)`` pairs, so :meth:`IncomingChannel.read_with_age` returns a value with
*its own* stamp, never a neighbour's.

An :class:`OutgoingChannel` is the writer end only: ``write`` stamps the value and stores it in
a lock-free ring (two preallocated slot lists, :mod:`rlbridge.csp.stamped_ring`: no allocation
per write); the send thread is its reader. With ``immediate=True`` (``through_buffer`` off) a
write also rings the send thread's doorbell, which costs a futex wake *only* when the send
thread sleeps; with ``through_buffer`` on, a write makes no system call at all and the value
leaves on ``Bridge.send()`` or the next send-loop tick. The ring is single-producer: a write
from a second thread while the first writer thread lives raises :class:`ChannelMisuseError`.
A value that cannot be the bound field's type raises at ``write`` (:mod:`.value_check`: one
``type(value) in accept`` test on the fast path), so a bad value never reaches the wire.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Sequence
from operator import itemgetter
from typing import Any, NamedTuple

from rlbridge.csp.channel import _MISSING, Channel, ChannelStatistics, Doorbell, _Missing
from rlbridge.csp.errors import ChannelClosed, SecondWriterError
from rlbridge.csp.health import ChannelHealth
from rlbridge.csp.stamped_ring import StampedRing
from rlbridge.csp.value_check import UNCHECKED, Mismatch, WrongValueType, compile_check
from rlbridge.wire import TopicAck
from rlbridge.wire.clock import ClockOffset, InterarrivalJitter
from rlbridge.wire.link import LinkMonitor
from rlbridge.wire.sequence import SequenceTracker


class AgedValue(NamedTuple):
    """A value and its age in ns (clock-corrected; ``-1`` for ``initial``, which has none)."""

    value: Any
    age_ns: int


_new_aged = tuple.__new__
_second = itemgetter(1)
#: Stands in for a link's clock before (or without) one: offset 0, error unknown.
_NO_CLOCK = ClockOffset()


class IncomingChannel(Channel[Any]):
    """Middleware -> control code. Read it like any buffered channel."""

    __slots__ = ("_clock", "_delivered", "_jitter", "_link", "_max_age_ns", "_one_way",
                 "_overtaken", "_tracker", "channel_id", "expired", "field", "last_stamp_ns",
                 "latest", "msg_type", "ros_lost", "topic", "transport")  # fmt: skip

    def __init__(self, channel_id: int, topic: str, msg_type: str, field: str | None, *,
                 transport: str, blocking: bool, buffer_size: int,
                 initial: Any | _Missing = _MISSING, latest: bool = False,
                 max_age_ms: int = 0, link: LinkMonitor | None = None) -> None:
        if max_age_ms < 0:
            raise ValueError(f"max_age_ms must be >= 0 (0: no limit), got {max_age_ms}")
        super().__init__(buffer_size, blocking=blocking,
                         initial=_MISSING if initial is _MISSING else (0, initial),
                         name=f"{topic} [{msg_type} {field or '<message>'}] in")
        self.channel_id = channel_id
        #: The server's count of this channel's values lost on the ROS side (-1: none yet).
        self.ros_lost = -1
        self.topic = topic
        self.msg_type = msg_type
        self.field = field
        self.transport = transport
        self.latest = latest
        self._max_age_ns = max_age_ms * 1_000_000
        self._link = link
        self._clock = link.clock if link is not None else _NO_CLOCK
        self.last_stamp_ns = 0
        self._tracker = SequenceTracker()
        self._jitter = InterarrivalJitter()
        self._one_way = -1
        self._overtaken = 0
        self._delivered = 0
        #: Values dropped on arrival for being older than ``max_age_ms``.
        self.expired = 0

    def restart_sequence(self) -> None:
        """The channel was bound again (reconnect): the server numbers from 0 again."""
        self._tracker.restart()

    def relink(self, link: LinkMonitor | None) -> None:
        """A new session has a new link monitor: RTT and clock offset come from it now."""
        self._link = link
        self._clock = link.clock if link is not None else _NO_CLOCK

    def deliver(self, first_seq: int, stamps: list[int], values: list[Any]) -> None:
        """Called by the receive thread with one packet's (or one read burst's) values.

        Per value only C-level work (slices, ``zip``); the measurements (jitter, one-way
        age) take the run's newest value, because a run's values share one arrival time.
        """
        n = len(values)
        start = self._tracker.accept_run(first_seq, n)
        if start >= n or self._closed:
            return
        if start:
            stamps, values = stamps[start:], values[start:]
        now = time.time_ns() + self._clock.offset_ns  # in the server's clock, like the stamps
        newest = stamps[-1]
        self._jitter.add(newest, now)
        age = now - newest
        self._one_way = age if self._one_way < 0 else self._one_way + (age - self._one_way) // 16
        if self._max_age_ns and stamps[0] < now - self._max_age_ns:
            cutoff = now - self._max_age_ns
            fresh = [(s, v) for s, v in zip(stamps, values, strict=True) if s >= cutoff]
            self.expired += len(values) - len(fresh)
            if not fresh:
                return
            stamps, values = [s for s, _ in fresh], [v for _, v in fresh]
        count = len(values)
        if self.latest and count > 1:
            self._overtaken += count - 1
            stamps, values, count = stamps[-1:], values[-1:], 1
        # Equal lengths: a Batch with unequal ones does not decode (packets.py).
        Channel.deliver_many(self, list(zip(stamps, values)))  # noqa: B905
        self._delivered += count
        # Set after the value is in the ring: a reader pairing ``last_stamp_ns`` with a value
        # read just before may see an older stamp (age over-, never under-estimated);
        # read_with_age() is exact.
        self.last_stamp_ns = stamps[-1]

    # -- reading: the ring holds (stamp, value) pairs -----------------------------------------
    def read(self, timeout: float | None = None) -> Any:
        return Channel.read(self, timeout)[1]

    def read_many(self, max_items: int | None = None) -> list[Any]:
        return list(map(_second, Channel.read_many(self, max_items)))

    def read_with_age(self, timeout: float | None = None) -> AgedValue:
        """Like :meth:`read`, with the value's age: now minus its stamp, across hosts.

        The stamp is the server's wall clock when the middleware delivered the value; the
        age is corrected by the heartbeat clock-offset estimate, to within half the round
        trip (``health().clock_error_ns``).
        """
        stamp, value = Channel.read(self, timeout)
        age = time.time_ns() + self._clock.offset_ns - stamp if stamp else -1
        return _new_aged(AgedValue, (value, age))  # tuple.__new__: no Python-level __new__

    def write(self, value: Any, timeout: float | None = None) -> None:
        """A local write (tests, simulation): stamped now, in the server's clock."""
        Channel.write(self, (time.time_ns() + self._clock.offset_ns, value), timeout)

    def deliver_many(self, values: Sequence[Any]) -> None:
        """A local bulk write (tests, simulation): stamped now, in the server's clock."""
        stamp = time.time_ns() + self._clock.offset_ns
        Channel.deliver_many(self, [(stamp, v) for v in values])

    @property
    def age_ns(self) -> int:
        """Age of the newest value delivered (-1 before the first one), clock-corrected."""
        stamp = self.last_stamp_ns
        return time.time_ns() + self._clock.offset_ns - stamp if stamp else -1

    @property
    def lost(self) -> int:
        """Values the server sent that never arrived (sequence gaps)."""
        return self._tracker.lost

    @property
    def duplicates(self) -> int:
        """Values that arrived twice (redundant UDP) or out of order, and were dropped."""
        return self._tracker.duplicates + self._tracker.stale

    def health(self) -> ChannelHealth:
        """A snapshot of this channel's delivery (csp/health.py); never blocks."""
        link = self._link
        tracker = self._tracker
        return ChannelHealth(
            rtt_ns=link.rtt_ns if link is not None else -1,
            one_way_ns=self._one_way,
            jitter_ns=self._jitter.jitter_ns if self._delivered else -1,
            lost=tracker.lost,
            duplicates=tracker.duplicates,
            overwritten=self._ring.overwritten,
            overtaken=self._overtaken + tracker.stale,
            expired=self.expired,
            values=self._delivered,
            clock_error_ns=self._clock.error_bound_ns,
            clock_offset_ns=self._clock.offset_ns,
            ros_lost=self.ros_lost,
        )


_get_ident = threading.get_ident


class OutgoingChannel:
    """Control code -> middleware. ``write`` never blocks and never touches a socket."""

    __slots__ = ("_accept", "_bell", "_check", "_clock", "_closed", "_discarded", "_expired",
                 "_held", "_history", "_link", "_max_age_ns", "_next_seq", "_overtaken", "_refused",
                 "_rejected", "_ring", "_within", "_writer", "channel_id", "field", "immediate",
                 "latest", "msg_type", "redundancy", "ros_lost", "topic", "transport")  # fmt: skip

    def __init__(self, channel_id: int, topic: str, msg_type: str, field: str | None, *,
                 transport: str, immediate: bool, buffer_size: int, doorbell: Doorbell,
                 redundancy: int = 0, latest: bool = False, max_age_ms: int = 0,
                 link: LinkMonitor | None = None) -> None:
        if buffer_size < 1:
            raise ValueError(f"an outgoing channel needs buffer_size >= 1, got {buffer_size}")
        if not 0 <= redundancy <= 16:
            raise ValueError(f"redundancy must be 0..16 previous values, got {redundancy}")
        if max_age_ms < 0:
            raise ValueError(f"max_age_ms must be >= 0 (0: no limit), got {max_age_ms}")
        self.channel_id = channel_id
        #: The server's count of this channel's values lost on the ROS side (-1: none yet).
        self.ros_lost = -1
        self.topic = topic
        self.msg_type = msg_type
        self.field = field
        self.transport = transport
        self.immediate = immediate
        self.latest = latest
        self.redundancy = redundancy if transport == "udp" else 0
        self._max_age_ns = max_age_ms * 1_000_000
        self._link = link
        self._clock = link.clock if link is not None else _NO_CLOCK
        self._ring = StampedRing(buffer_size)
        self._bell = doorbell
        self._next_seq = 0
        self._closed = False
        self._writer = 0
        # Send-thread state: a latest value held back while TCP is backed up, and the last
        # ``redundancy`` values sent (repeated in front of new ones on UDP).
        self._held: tuple[int, Any] | None = None
        self._history: deque[tuple[int, int, Any]] = deque(maxlen=max(self.redundancy, 1))
        self._overtaken = 0
        self._expired = 0
        self._discarded = 0
        self._accept, self._check, self._within = UNCHECKED[0], UNCHECKED[1], UNCHECKED.within
        self._rejected = self._refused = 0  # refused at ``write``; by the server

    def bound(self, ack: TopicAck) -> None:
        """The server's answer: the type's normalised name, and the schema values must match."""
        self.msg_type, check = ack.msg_type, compile_check(ack.schema)
        self._accept, self._check, self._within = check.accept, check.coerce, check.within

    def refused(self, count: int) -> None:  # receive thread: counted in health().rejected
        """The server refused ``count`` values of this channel (``Error`` BAD_VALUE)."""
        self._refused += count

    def _wrong(self, exc: Mismatch) -> WrongValueType:
        self._rejected += 1
        return WrongValueType(self.topic, self.msg_type, self.field, exc)

    def _check_writer(self) -> None:
        """Slow path: a thread other than the recorded writer writes (module docstring)."""
        me = threading.get_ident()
        owner = self._writer
        if owner and any(t.ident == owner for t in threading.enumerate()):
            raise SecondWriterError(self.topic, owner, me)
        self._writer = me  # first write, or the previous writer thread has ended

    def write(self, value: Any) -> None:
        """Queue one value for the send thread; a full buffer drops its oldest value (counted).
        A value that cannot be the field's type raises ``WrongValueType`` (a TypeError)."""
        if self._closed:
            raise ChannelClosed(self.topic)
        if _get_ident() != self._writer:
            self._check_writer()
        if type(value) not in self._accept or (self._within is not None
                                               and value not in self._within):
            try:
                value = self._check(value)
            except Mismatch as exc:
                raise self._wrong(exc) from None
        self._ring.push_stamped(time.time_ns(), value)
        if self.immediate:
            bell = self._bell
            if bell.waiting:
                bell.ring()

    def write_many(self, values: Sequence[Any]) -> None:
        """Queue a batch (one stamp for all): the cheapest way to move many values."""
        if self._closed:
            raise ChannelClosed(self.topic)
        if _get_ident() != self._writer:
            self._check_writer()
        accept = self._accept if self._within is None else ()
        if not all(type(v) in accept for v in values):
            try:
                values = [v if type(v) in accept else self._check(v) for v in values]
            except Mismatch as exc:
                raise self._wrong(exc) from None
        self._ring.push_many_stamped(time.time_ns(), values)
        if self.immediate:
            bell = self._bell
            if bell.waiting:
                bell.ring()

    def relink(self, link: LinkMonitor | None) -> None:
        """A new session has a new link monitor: RTT and clock offset come from it now."""
        self._link = link
        self._clock = link.clock if link is not None else _NO_CLOCK

    def pending(self) -> int:
        """Values written and not yet taken by the send thread (a snapshot, for monitors)."""
        return len(self._ring)

    @property
    def holding(self) -> bool:
        """Send thread: a latest value waits for the TCP connection to drain."""
        return self._held is not None

    def take(self, congested: bool = False) -> tuple[int, list[int], list[Any], int]:
        """Send thread: what to send now, as ``(first_seq, stamps, values, repeated)``.

        Applies the policies: values older than ``max_age_ms`` are dropped (``expired``); a
        ``latest`` channel sends only its newest value (the rest ``overtaken``) and, while
        ``congested``, holds it back instead, to be replaced by newer ones; a UDP channel with
        ``redundancy`` k puts the previous k values (``repeated`` of them) in front. Sequence
        numbers are given here, so discarded values leave no gap the server would call lost.
        """
        stamps, values = self._ring.drain_stamped()
        if self._max_age_ns and values:
            cutoff = time.time_ns() - self._max_age_ns
            keep = [i for i, s in enumerate(stamps) if s >= cutoff]
            if len(keep) < len(values):
                self._expired += len(values) - len(keep)
                stamps = [stamps[i] for i in keep]
                values = [values[i] for i in keep]
        if self.latest:
            held = self._held
            if values:
                self._overtaken += len(values) - 1 + (held is not None)
                held = (stamps[-1], values[-1])
            if held is None:
                return self._next_seq, [], [], 0
            if congested:
                self._held = held
                return self._next_seq, [], [], 0
            self._held = None
            stamps, values = [held[0]], [held[1]]
        first = self._next_seq
        n = len(values)
        self._next_seq = first + n
        if not self.redundancy or n == 0:
            return first, stamps, values, 0
        history = self._history
        old = list(history)
        history.extend((first + i, stamps[i], values[i])
                       for i in range(max(0, n - self.redundancy), n))
        if not old:
            return first, stamps, values, 0
        # The previous k values in front: one lost datagram loses no value (the server
        # drops the copies it already has by sequence number).
        return (old[0][0], [s for _, s, _ in old] + stamps, [v for _, _, v in old] + values,
                len(old))

    def statistics(self) -> ChannelStatistics:
        """Counters as for a :class:`Channel`; ``overwritten`` is what a full buffer dropped."""
        ring = self._ring
        return ChannelStatistics(buffered=len(ring), overwritten=ring.overwritten,
                                 dropped=self._discarded,
                                 written=ring.written, read=ring.popped, waiting_readers=0,
                                 waiting_writers=0, closed=self._closed)

    def health(self) -> ChannelHealth:
        """A snapshot of this channel's sending (csp/health.py); never blocks.

        One-way latency here is half the round trip; loss and jitter of this direction are
        measured by the server (``Bridge.server_stats()``, per channel).
        """
        link = self._link
        rtt = link.rtt_ns if link is not None else -1
        ring = self._ring
        return ChannelHealth(
            rtt_ns=rtt, one_way_ns=rtt // 2 if rtt >= 0 else -1, jitter_ns=-1, lost=-1,
            duplicates=0, overwritten=ring.overwritten, overtaken=self._overtaken,
            expired=self._expired, values=ring.written,
            clock_error_ns=self._clock.error_bound_ns, clock_offset_ns=self._clock.offset_ns,
            rejected=self._rejected + self._refused, ros_lost=self.ros_lost)

    @property
    def closed(self) -> bool:
        """True after :meth:`close` (``Bridge.unsubscribe`` or ``Bridge.close``)."""
        return self._closed

    def close(self) -> None:
        """Refuse further writes. A latest value still held back is discarded, counted in
        ``statistics().dropped`` (the Bridge flushes before closing, so only one that the
        connection never let through)."""
        self._closed = True
        if self._held is not None:
            self._held = None
            self._discarded += 1
