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

The :class:`~rlbridge.client.channels.outgoing.OutgoingChannel` (the writer end, control code -> the
middleware) lives in :mod:`rlbridge.client.channels.outgoing` and is re-exported here.

A blocking TCP subscription that is not ``latest`` is flow-controlled (docs/policies.md): the
server sends at most ``buffer_size`` values beyond what the reader has consumed, so the ring
never overwrites one; each read that frees a quarter of the ring has the send thread grant the
server more (``Credit``), so the reader's pace sets the publisher's.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from operator import itemgetter
from typing import Any, NamedTuple

from mypy_extensions import mypyc_attr

from rlbridge.client.channels.health import ChannelHealth
from rlbridge.client.channels.outgoing import OutgoingChannel
from rlbridge.csp.bell import Bell
from rlbridge.csp.channel import _MISSING, Channel, _Missing
from rlbridge.errors import ChannelMisuseError, SecondWriterError

__all__ = ["AgedValue", "IncomingChannel", "OutgoingChannel", "SecondWriterError"]
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


# Compiled by mypyc (rlbridge/_compiled.py); GuardedChannel (client/channels/failsafe.py)
# subclasses it.
@mypyc_attr(allow_interpreted_subclasses=True)
class IncomingChannel(Channel[Any]):
    """Middleware -> control code: what ``Bridge.subscribe`` returns.

    Read it like any buffered :class:`Channel` (``read``, ``try_read``, ``read_many``;
    ``read_with_age`` adds each value's age); ``health()`` reports its delivery (RTT, jitter,
    loss, age), ``statistics()`` its buffer. ``close()`` (or leaving a ``with`` block) unbinds
    the topic. ``write`` stores a value locally, as if it had arrived (tests, simulation).
    """

    __slots__ = ("_arrived", "_clock", "_credit_bell", "_credit_step", "_delivered",
                 "_jitter", "_link", "_max_age_ns", "_one_way", "_overtaken", "_tracker",
                 "channel_id", "credited", "expired", "field", "last_stamp_ns", "latest",
                 "msg_type", "on_close", "ros_lost", "topic", "transport")  # fmt: skip

    def __init__(self, channel_id: int, topic: str, msg_type: str, field: str | None, *,
                 transport: str, blocking: bool, buffer_size: int,
                 initial: Any | _Missing = _MISSING, latest: bool = False,
                 max_age_ms: int = 0, link: LinkMonitor | None = None,
                 credit_bell: Bell | None = None) -> None:
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
        # Credit flow control (module docstring): the send thread's doorbell, rung by a read
        # that frees ``_credit_step`` slots; values of this binding that arrived; and the
        # limit last granted (the server starts from the ring's size).
        self._credit_bell = credit_bell
        self._credit_step = max(1, buffer_size // 4)
        self._arrived = 0
        self.credited = buffer_size
        #: Called once by the first :meth:`close` (the Bridge unbinds the topic there).
        self.on_close: Callable[[IncomingChannel], None] | None = None

    def close(self) -> None:
        """Unbind the topic on the server (as ``Bridge.unsubscribe``) and close the channel:
        values already here stay readable, then reads raise ``ChannelClosed``; idempotent."""
        Channel.close(self)
        hook = self.on_close
        if hook is not None:
            self.on_close = None
            hook(self)

    def __enter__(self) -> IncomingChannel:
        return self

    @property
    def flow(self) -> bool:
        """True for a flow-controlled channel (the server sends within its credit)."""
        return self._credit_bell is not None

    def restart_sequence(self) -> int:
        """The channel was bound again (reconnect): the server numbers from 0 again. Returns
        the new binding's first credit, the ring's free room: values of the old binding
        still unread keep their slots (the request's ``buffer_size``, protocol.md 10.5)."""
        self._tracker.restart()
        self._arrived = 0
        room: int = self._ring.capacity - len(self._ring)
        self.credited = room
        return room

    def credit_limit(self) -> int:
        """The values the server may have sent: consumed ones plus a free ring.

        Read by the send thread while the receive thread delivers: ``_arrived`` is read
        first and raised only after the ring holds the values, so a race can only make
        the limit smaller than it could be, never let the ring overflow.
        """
        return self._arrived - len(self._ring) + self._ring.capacity

    def credit_due(self) -> bool:
        """Send thread: enough was consumed since the last credit to grant more."""
        return self.credit_limit() - self.credited >= self._credit_step

    def _consumed(self) -> None:
        """After a read of a flow-controlled channel: wake the send thread to grant credit."""
        bell = self._credit_bell
        if bell is not None and bell.waiting and self.credit_due():
            bell.ring()

    def relink(self, link: LinkMonitor | None) -> None:
        """A new session has a new link monitor: RTT and clock offset come from it now."""
        self._link = link
        self._clock = link.clock if link is not None else _NO_CLOCK

    def deliver(self, first_seq: int, stamps: list[int], values: list[Any]) -> None:
        """Called by the receive thread with one packet's (or one read burst's) values.

        Per value only C-level work (slices, ``zip``, one slice store into the ring); the
        measurements (jitter, one-way age) take the run's newest value, because a run's
        values share one arrival time. The common case (the run continues the sequence, no
        ``max_age_ms``, not ``latest``) makes two Python calls, the jitter estimate and the
        ring write: the sequence tracker's in-order case and ``Channel.deliver_many`` are
        inlined here, and one value is stored without ``zip`` (the receive thread runs this
        once per channel per wake-up); ``tests/client/test_incoming_deliver.py`` checks it
        against the general path.
        """
        # inlines: SequenceTracker.accept_run, Channel.deliver_many, moving_average
        n = len(values)
        tracker = self._tracker
        highest = tracker.highest
        if n and first_seq == highest + 1:  # SequenceTracker.accept_run's in-order case
            tracker.highest = highest + n
            tracker.accepted += n
            start = 0
        else:
            start = tracker.accept_run(first_seq, n)
            if start >= n:
                return
        if self._closed:
            return
        if start:
            stamps, values = stamps[start:], values[start:]
        try:
            now = time.time_ns() + self._clock.offset_ns  # the server's clock, like the stamps
            newest = stamps[-1]
            self._jitter.add(newest, now)
            age = now - newest
            one_way = self._one_way
            self._one_way = age if one_way < 0 else one_way + (age - one_way) // 16
            if self._max_age_ns or self.latest:
                kept = self._apply_policies(stamps, values, now)
                if kept is None:
                    return
                stamps, values = kept
            # Channel.deliver_many, inlined (the channel is open and buffered; a close racing
            # this write leaves the values readable before ChannelClosed, as a write just
            # before the close would).
            token = self._write_token
            try:
                token.pop()
            except IndexError:
                raise ChannelMisuseError(self._name, "writer") from None
            count = len(values)
            try:
                if count == 1:  # one value per wake-up (a control loop's rate): no zip, no list
                    self._ring.push_overwrite((stamps[0], values[0]))
                else:
                    # Equal lengths: a Batch with unequal ones does not decode (packets.py).
                    self._ring.push_many(list(zip(stamps, values)), overwrite=True)  # noqa: B905
            finally:
                token.append(None)
            bell = self._bell
            if bell.waiting:
                bell.ring()
            self._delivered += count
            # Set after the value is in the ring: a reader pairing ``last_stamp_ns`` with a
            # value read just before may see an older stamp (age over-, never
            # under-estimated); read_with_age() is exact.
            self.last_stamp_ns = stamps[-1]
        finally:
            self._arrived += n - start  # after the ring has them: see credit_limit

    def _apply_policies(self, stamps: list[int], values: list[Any], now: int
                        ) -> tuple[list[int], list[Any]] | None:
        """``max_age_ms`` and ``latest`` (docs/policies.md): what is left, ``None`` if nothing."""
        if self._max_age_ns and stamps[0] < now - self._max_age_ns:
            cutoff = now - self._max_age_ns
            fresh = [(s, v) for s, v in zip(stamps, values, strict=True) if s >= cutoff]
            self.expired += len(values) - len(fresh)
            if not fresh:
                return None
            stamps, values = [s for s, _ in fresh], [v for _, v in fresh]
        count = len(values)
        if self.latest and count > 1:
            self._overtaken += count - 1
            stamps, values = stamps[-1:], values[-1:]
        return stamps, values

    # -- reading: the ring holds (stamp, value) pairs -----------------------------------------
    def read(self, timeout: float | None = None) -> Any:
        """The next value (blocking channel: waits up to ``timeout``, then ``TimeoutError``)
        or, non-blocking, the newest again when nothing is new (``initial`` before the first;
        with neither, ``NoValueYet``). ``try_read`` never waits (``WouldBlock``)."""
        value = Channel.read(self, timeout)[1]
        if self._credit_bell is not None:
            self._consumed()
        return value

    def read_many(self, max_items: int | None = None) -> list[Any]:
        """Every value not read yet (at most ``max_items``), oldest first, without waiting;
        ``[]`` when nothing is new (the newest is not repeated here)."""
        values = list(map(_second, Channel.read_many(self, max_items)))
        if self._credit_bell is not None:
            self._consumed()
        return values

    def read_with_age(self, timeout: float | None = None) -> AgedValue:
        """Like :meth:`read`, with the value's age: now minus its stamp, across hosts.

        The stamp is the server's wall clock when the middleware delivered the value; the
        age is corrected by the heartbeat clock-offset estimate, to within half the round
        trip (``health().clock_error_ns``).
        """
        stamp, value = Channel.read(self, timeout)
        if self._credit_bell is not None:
            self._consumed()
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
        """A snapshot of this channel's delivery (client/channels/health.py); never blocks."""
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
