"""The outgoing bridge channel: control code -> a topic on the middleware.

``write`` stamps the value and stores it in a lock-free ring (two preallocated slot lists,
:mod:`rlbridge.csp.stamped_ring`: no allocation per write); the send thread is the reader
(:meth:`OutgoingChannel.take`; a ``plain`` channel:
:func:`~rlbridge.client.session.plain_round.take_plain`).
With ``through_buffer`` off a write rings the send thread's bell, a futex wake *only* when that
thread sleeps; with it on, a write makes no system call and the value leaves on
``Bridge.send()`` or the send loop's tick. The ring is single-producer: a second writer thread
gets :class:`ChannelMisuseError`, and so do the reading verbs (the SDK is the reader).
What may leave when is the channel's :class:`~rlbridge.client.channels.pacing.Pacing` (credit of a
flow-controlled channel, ``max_rate_hz``); what it holds back stays in the ring, visible to
control code (``writable``, ``wait_writable``). The server's loss reports land in
:meth:`OutgoingChannel.on_loss`, so ``health()`` shows first-hop loss.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Any

from rlbridge.client.channels.health import ChannelHealth
from rlbridge.client.channels.pacing import Pacing
from rlbridge.client.channels.value_check import UNCHECKED, Mismatch, compile_check
from rlbridge.csp.bell import Bell
from rlbridge.csp.channel import Doorbell
from rlbridge.csp.stamped_ring import StampedRing
from rlbridge.csp.statistics import ChannelStatistics
from rlbridge.errors import ChannelClosed, ChannelMisuseError, SecondWriterError, WrongValueType
from rlbridge.wire import TopicAck
from rlbridge.wire.bundle import BATCH_TAG, VALUE_TAG, Part
from rlbridge.wire.clock import ClockOffset
from rlbridge.wire.link import LinkMonitor
from rlbridge.wire.packets import ChannelLoss

#: Stands in for a link's clock before (or without) one: offset 0, error unknown.
_NO_CLOCK = ClockOffset()

_get_ident = threading.get_ident
_time_ns = time.time_ns


def _no_reader(topic: str, verb: str) -> ChannelMisuseError:
    return ChannelMisuseError(f"{topic} out", "reader", (
        f"{verb}() on outgoing channel {topic!r}: its reader is the SDK's send thread, which "
        "publishes every value written here; to read the topic, subscribe to it"))


class OutgoingChannel:
    """Control code -> middleware (``Bridge.publish``). ``write``/``try_write`` never wait
    or touch a socket: a full buffer drops its oldest value (``statistics().overwritten``);
    the reading verbs raise ``ChannelMisuseError``; ``close()``/``with`` unbind the topic."""

    __slots__ = ("_accept", "_bell", "_check", "_clock", "_closed", "_discarded", "_expired",
                 "_held", "_history", "_hop", "_hop_base", "_left_out", "_link", "_max_age_ns",
                 "_next_seq", "_overtaken", "_refused", "_rejected", "_ring", "_space",
                 "_unconfirmed", "_within", "_writer",
                 "channel_id", "deferred", "field", "flow", "immediate", "latest", "msg_type",
                 "on_close", "pacing", "plain", "redundancy", "ros_lost", "topic",
                 "transport")  # fmt: skip

    def __init__(self, channel_id: int, topic: str, msg_type: str, field: str | None, *,
                 transport: str, immediate: bool, buffer_size: int, doorbell: Bell,
                 redundancy: int = 0, latest: bool = False, max_age_ms: int = 0,
                 link: LinkMonitor | None = None, max_rate_hz: float | None = None,
                 adapt_rate: bool = False, flow: bool = False) -> None:
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
        #: Rate limit and credit (client/channels/pacing.py); None: everything may leave at once.
        self.pacing = (None if max_rate_hz is None and not flow else
                          Pacing(max_rate_hz, adapt=adapt_rate, now_ns=time.monotonic_ns()))
        #: Asked the server for credit flow control (TCP, not latest; docs/policies.md).
        self.flow = flow
        #: Send thread: the last take left values behind (rate limit or credit).
        self.deferred = False
        #: No policy between the ring and the wire (UDP; no rate limit, credit, latest, age
        #: limit or redundancy): the send thread takes it with :meth:`take_parts`.
        self.plain = (transport == "udp" and self.pacing is None and not latest
                      and not max_age_ms and not self.redundancy)
        #: Rung by the send thread after taking values, while a writer waits for room.
        self._space = Doorbell()
        #: The server's last loss report for this binding, and the totals of earlier ones.
        self._hop: ChannelLoss | None = None
        self._hop_base = (0, 0)
        #: Values the server had not confirmed when the session was closed (goodbye.py).
        self._unconfirmed = 0
        self._accept, self._check, self._within = UNCHECKED[0], UNCHECKED[1], UNCHECKED.within
        # ``health().rejected`` sums three counters, each written by one thread only, so no
        # update is lost without a lock: refused at ``write`` (the writer), by the server (the
        # receive thread), left out by the send thread (too large to send).
        self._rejected = self._refused = self._left_out = 0
        self.on_close: Callable[[OutgoingChannel], None] | None = None

    def bound(self, ack: TopicAck) -> None:
        """The server's answer: the type's normalised name, the schema values must match,
        and (flow control) the first credit."""
        self.msg_type, check = ack.msg_type, compile_check(ack.schema)
        self._accept, self._check, self._within = check.accept, check.coerce, check.within
        if ack.credit is not None:
            self.on_credit(ack.credit)

    def refused(self, count: int) -> None:  # counted in health().rejected
        """Receive thread only: the server refused ``count`` values (``Error`` BAD_VALUE)."""
        self._refused += count

    def left_out(self, count: int) -> None:  # counted in health().rejected
        """Send thread only: ``count`` values too large to send (one alone over the server's
        ``max_packet``, or over a datagram), never sent. Its own counter, not ``_refused``,
        which the receive thread writes meanwhile (``+=`` is no atomic update)."""
        self._left_out += count

    def _wrong(self, exc: Mismatch) -> WrongValueType:
        self._rejected += 1
        return WrongValueType(self.topic, self.msg_type, self.field, exc.path, exc.expected,
                              exc.value)

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
        self._ring.push_stamped(_time_ns(), value)
        if self.immediate:
            bell = self._bell
            if bell.waiting:
                bell.ring()

    def try_write(self, value: Any) -> None:
        """:meth:`write`, which never waits; the name every channel has for a write."""
        self.write(value)

    def read(self, timeout: float | None = None) -> Any:
        """Refused with :class:`ChannelMisuseError`: this channel's reader is the SDK."""
        raise _no_reader(self.topic, "read")

    def try_read(self) -> Any:
        """Refused with :class:`ChannelMisuseError`: this channel's reader is the SDK."""
        raise _no_reader(self.topic, "try_read")

    def read_many(self, max_items: int | None = None) -> list[Any]:
        """Refused with :class:`ChannelMisuseError`: this channel's reader is the SDK."""
        raise _no_reader(self.topic, "read_many")

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
        self._ring.push_many_stamped(_time_ns(), values)
        if self.immediate:
            bell = self._bell
            if bell.waiting:
                bell.ring()

    def relink(self, link: LinkMonitor | None) -> None:
        """A new session has a new link monitor: RTT and clock offset come from it now."""
        self._link = link
        self._clock = link.clock if link is not None else _NO_CLOCK

    def restart_sequence(self) -> None:
        """Bound again (reconnect): number from 0, wait for the new binding's credit.

        Send thread paused (the Bridge binds again before it resumes), so no take runs.
        """
        self._next_seq = 0
        self._history.clear()
        hop = self._hop
        if hop is not None:
            self._hop_base = (self._hop_base[0] + hop.received, self._hop_base[1] + hop.lost)
            self._hop = None
        if self.pacing is not None:
            self.pacing.limit = None

    def pending(self) -> int:
        """Values written and not yet taken by the send thread (a snapshot, for monitors)."""
        return len(self._ring)

    @property
    def writable(self) -> int:
        """Values the ring takes before a write overwrites an unsent one."""
        return self._ring.capacity - len(self._ring)

    def wait_writable(self, timeout: float | None = None) -> bool:
        """Block until a write would not overwrite (or ``timeout``); False on timeout. For a
        writer that must lose nothing on a flow-controlled channel (it waits at the readers'
        pace); a hard-real-time loop reads :attr:`writable` instead."""
        ring = self._ring
        return self._space.wait_for(lambda: self._closed or len(ring) < ring.capacity,
                                    timeout)

    def ready(self, now_ns: int) -> bool:
        """Send thread: values wait in the ring and may leave now (credit and rate allow
        one). A held latest value is not counted: the thread re-checks it on its own poll."""
        if not len(self._ring):
            return False
        pacing = self.pacing
        return pacing is None or pacing.allowance(self._next_seq, now_ns) > 0

    def retry_in(self, now_ns: int) -> float | None:
        """Send thread: seconds until the rate limit lets a waiting value go (None: never
        by itself; credit rings the doorbell when it arrives)."""
        pacing = self.pacing
        if pacing is None or not (len(self._ring) or self._held is not None):
            return None
        return pacing.wait_s(now_ns)

    def on_credit(self, limit: int) -> bool:
        """Receive thread: the server granted credit; True if values may now go."""
        return self.pacing is not None and self.pacing.on_credit(limit)

    def on_loss(self, loss: ChannelLoss) -> int:
        """Receive thread: the server's loss report for this channel; returns the values
        newly lost since the previous report (counts are per binding, cumulative)."""
        before = self._hop
        self._hop = loss
        received = loss.received - (before.received if before is not None else 0)
        lost = loss.lost - (before.lost if before is not None else 0)
        if self.pacing is not None:
            self.pacing.on_report(received, lost)
        return lost

    def unconfirmed(self) -> int:
        """Values sent in this binding that the server's last loss report does not cover
        (its ``next_seq``): in flight, or lost. Read by the goodbyes of ``Bridge.close`` and
        ``close()`` (goodbye.py)."""
        hop = self._hop
        return max(0, self._next_seq - (hop.next_seq if hop is not None else 0))

    def not_confirmed(self, count: int) -> None:
        """The session or binding ended with ``count`` values unconfirmed: counted in
        ``health().lost`` (the client cannot tell whether they arrived)."""
        self._unconfirmed += count

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
        pacing = self.pacing
        allowed = None
        if pacing is not None:
            allowed = pacing.allowance(self._next_seq, time.monotonic_ns())
        stamps, values = self._ring.drain_stamped(None if self.latest else allowed)
        self.deferred = allowed is not None and len(self._ring) > 0
        if self._space.waiting:
            self._space.ring()
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
            if congested or allowed == 0:
                self._held = held
                return self._next_seq, [], [], 0
            self._held = None
            stamps, values = [held[0]], [held[1]]
        first = self._next_seq
        n = len(values)
        self._next_seq = first + n
        if pacing is not None:
            pacing.spend(n)
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

    def take_parts(self, parts: list[Part], max_batch: int) -> int:
        """Send thread, a :attr:`plain` channel: append what waits to ``parts``; return how
        many values that was (``plain_round.take_plain`` has the common case inline).

        :meth:`take` without its policies: each part is a tuple shaped like the ``Value`` (or
        ``Batch`` of at most ``max_batch``) it stands for (:mod:`rlbridge.wire.bundle`), so
        no packet object is made per value.
        """
        stamps, values = self._ring.drain_stamped()
        if self._space.waiting:
            self._space.ring()
        n = len(values)
        first = self._next_seq
        self._next_seq = first + n
        cid = self.channel_id
        if n == 1 or max_batch == 1:  # one value per packet: a Value each
            parts.extend([(VALUE_TAG, cid, first + i, stamps[i], values[i]) for i in range(n)])
        else:
            parts.extend([(BATCH_TAG, cid, first + i, stamps[i : i + max_batch],
                           values[i : i + max_batch]) for i in range(0, n, max_batch)])
        return n

    def statistics(self) -> ChannelStatistics:
        """Counters as for a :class:`Channel`; ``overwritten`` is what a full buffer dropped."""
        ring = self._ring
        return ChannelStatistics(buffered=len(ring), overwritten=ring.overwritten,
                                 dropped=self._discarded,
                                 written=ring.written, read=ring.popped, waiting_readers=0,
                                 waiting_writers=0, closed=self._closed)

    def health(self) -> ChannelHealth:
        """A snapshot of this channel's sending (client/channels/health.py); never blocks.

        One-way latency here is half the round trip. ``lost`` and ``arrived`` are the
        server's first-hop counts from its loss reports (every heartbeat period while they
        move; -1 before the first), totalled over reconnects; ``lost`` also counts the values
        the server had not confirmed when ``Bridge.close`` gave up waiting (goodbye.py).
        """
        link = self._link
        rtt = link.rtt_ns if link is not None else -1
        ring = self._ring
        hop, (base_received, base_lost) = self._hop, self._hop_base
        unconfirmed = self._unconfirmed
        reported = hop is not None or base_received or base_lost or unconfirmed
        pacing = self.pacing
        rate = -1 if pacing is None or pacing.rate_hz is None else int(pacing.rate_hz)
        return ChannelHealth(
            rtt_ns=rtt, one_way_ns=rtt // 2 if rtt >= 0 else -1, jitter_ns=-1,
            lost=base_lost + (hop.lost if hop else 0) + unconfirmed if reported else -1,
            duplicates=0, overwritten=ring.overwritten, overtaken=self._overtaken,
            expired=self._expired, values=ring.written,
            clock_error_ns=self._clock.error_bound_ns, clock_offset_ns=self._clock.offset_ns,
            arrived=base_received + (hop.received if hop else 0) if reported else -1,
            rate_limit_hz=rate, rejected=self._rejected + self._refused + self._left_out,
            ros_lost=self.ros_lost)

    @property
    def closed(self) -> bool:
        """True after :meth:`close` (``Bridge.unsubscribe`` or ``Bridge.close``)."""
        return self._closed

    @property
    def name(self) -> str:
        """The name used in errors: the topic and the direction."""
        return f"{self.topic} out"

    def close(self) -> None:
        """Refuse further writes, deliver what was written, then unbind the topic (as
        ``Bridge.unsubscribe``); idempotent. A latest value held back is discarded
        (``statistics().dropped``).

        Delivered: sent, and on UDP confirmed by the server's loss reports, bounded by the link
        timeout; what is unconfirmed then counts in ``health().lost``, with a warning
        (:mod:`rlbridge.client.session.goodbye`)."""
        self._closed = True
        self._space.ring()
        if self._held is not None:
            self._held = None
            self._discarded += 1
        hook = self.on_close
        if hook is not None:
            self.on_close = None
            hook(self)

    def __enter__(self) -> OutgoingChannel:
        return self

    def __exit__(self, et: type[BaseException] | None, e: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

