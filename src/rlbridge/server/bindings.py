"""Channel bindings: a client channel joined to one middleware publisher or subscription.

``Inbound`` carries client values into the middleware (the thesis's run-time binding
publisher); ``Outbound`` carries middleware values to the client (its topic listener). Both are
transport-agnostic: an outbound binding writes to whatever sink its channel chose.

Channel policies (docs/policies.md) live here on the server side. Inbound: duplicates from
redundant datagrams are dropped by sequence number, values older than ``max_age_ms``
(clock-corrected) are dropped before publishing (``expired``), and a ``latest`` channel
publishes only the newest value of each packet (``overtaken``). Outbound: values are stamped
when the middleware delivered them; a ``latest`` channel whose TCP connection is backed up
(:mod:`rlbridge.tcpstate`) holds only its newest value and writes it once the connection
drains, counting every value it replaces (``overtaken``). A channel under credit flow control
(TCP, not ``latest``; :mod:`rlbridge.server.flow`) sends within the client's credit instead of
dropping at a full socket buffer, and grants its publisher credit as the topic's subscribers
make room.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import deque
from collections.abc import Sequence
from typing import Any

from rlbridge.adapters.base import Publisher, Subscription, ValueSpec
from rlbridge.server.admission import (
    ValuesRefused,
    exact_check,
    publish_valid,
    value_converter,
    value_schema,
)
from rlbridge.server.flow import InboundCredit, OutboundCredit
from rlbridge.server.sinks import PacketSink
from rlbridge.wire import Batch, ChannelLoss, TopicConnect, Value
from rlbridge.wire.clock import ClockOffset, InterarrivalJitter, moving_average
from rlbridge.wire.sequence import SequenceTracker

#: How often a held latest value re-checks whether its TCP connection has drained.
HOLD_POLL_S = 0.001


class _NoValue:
    """A type no decoded value has: ``Inbound._exact_type`` when the fast test does not apply."""


class Inbound:
    """Client -> middleware. Duplicates and overtaken values (UDP) are dropped and counted."""

    def __init__(
        self, channel: int, spec: ValueSpec, publisher: Publisher, request: TopicConnect,
        clock: ClockOffset | None = None,
    ) -> None:
        self.channel = channel
        self.request = request
        self.spec = spec
        self._publisher = publisher
        self._convert = value_converter(spec)
        #: What the TopicAck tells the client about the values it may write.
        self.schema = value_schema(spec)
        #: For one value per packet (the common case): a value accepted unchanged skips
        #: ``_convert`` and its list checks; anything else still goes through it.
        self._exact = exact_check(spec.python_type)
        #: The same test without a call when the type is plain ``float``, ``bool`` or ``str``
        #: (``exact`` is then ``type(v) is ...``); ``_NoValue`` matches no value.
        self._exact_type: type = (spec.python_type if spec.python_type in (float, bool, str)
                                  else _NoValue)
        self._clock = clock
        self._max_age_ns = request.max_age_ms * 1_000_000
        self.tracker = SequenceTracker()
        self.jitter = InterarrivalJitter()
        self.one_way_ns = -1
        self.values_in = 0
        self.bad_values = 0
        self.expired = 0
        self.overtaken = 0
        #: Packets for this channel that did not decode (counted by the session).
        self.malformed = 0
        #: Values the session's ``--max-rate`` refused (reported in ``LossReport``).
        self.refused = 0
        #: Credit granted to the publisher, for a flow-controlled channel (server/flow.py).
        self.credit: InboundCredit | None = None

    def loss(self) -> ChannelLoss:
        """The first hop as this server saw it, for the client's ``LossReport``."""
        t = self.tracker
        return ChannelLoss(self.channel, t.accepted, t.lost, t.highest + 1, self.refused)

    def on_value(self, packet: Value, wall_ns: int | None = None) -> None:
        """``_admit`` for one value, inlined: this runs once per value on a busy server.

        ``wall_ns`` is when its datagram arrived (CLOCK_REALTIME; a bundle's parts share one
        reading), else now. The common case (the next sequence number, no credit, fresh, a
        value of the channel's type as it is) costs no Python call but the publish.
        """
        # inlines: Inbound._admit, Inbound._track_age
        # inlines: SequenceTracker.accept, InterarrivalJitter.add, moving_average
        tracker = self.tracker
        seq = packet.seq
        if seq == tracker.highest + 1:  # in order: what SequenceTracker.accept does for it
            tracker.highest = seq
            tracker.accepted += 1
        elif not tracker.accept(seq):
            return
        if self.credit is not None:  # publish first, then grant: as on_batch (server/flow.py)
            self._publish_flow([packet.stamp_ns], [packet.value])
            return
        stamp = packet.stamp_ns
        clock = self._clock
        now = ((time.time_ns() if wall_ns is None else wall_ns)
               + (clock.offset_ns if clock is not None else 0))  # the client's clock
        age = now - stamp  # the transit time: jitter.add and _track_age, inlined
        jitter = self.jitter
        last = jitter.last_transit
        jitter.last_transit = age
        if last is not None:
            jitter.jitter_ns += (abs(age - last) - jitter.jitter_ns) // 16
        one_way = self.one_way_ns
        self.one_way_ns = age if one_way < 0 else one_way + (age - one_way) // 16
        if self._max_age_ns and age > self._max_age_ns:
            self.expired += 1
            return
        value = packet.value
        if type(value) is self._exact_type or (self._exact is not None and self._exact(value)):
            self.values_in += 1
            self._publisher.publish([value])
        else:
            self._publish([value])

    def on_batch(self, packet: Batch) -> None:
        start = self.tracker.accept_run(packet.first_seq, len(packet.values))
        if start < len(packet.values):
            stamps, values = packet.stamps, packet.values
            if start:
                stamps, values = stamps[start:], values[start:]
            if self.credit is not None:
                self._publish_flow(stamps, values)
            else:
                self._admit(stamps, values)

    def _publish_flow(self, stamps: list[int], values: list[Any]) -> None:
        """Publish, then grant the publisher what the topic's subscribers have room for."""
        assert self.credit is not None
        try:
            self._admit(stamps, values)
        finally:
            self.credit.grant(self.tracker.highest + 1)

    def _admit(self, stamps: list[int], values: list[Any]) -> None:
        """New values: measure them, apply ``max_age_ms`` and ``latest``, publish the rest."""
        clock = self._clock
        now = time.time_ns() + (clock.offset_ns if clock is not None else 0)  # client clock
        for stamp in stamps:
            self.jitter.add(stamp, now)
        self._track_age(now - stamps[-1])
        if self._max_age_ns:
            cutoff = now - self._max_age_ns
            fresh = [v for s, v in zip(stamps, values, strict=True) if s >= cutoff]
            self.expired += len(values) - len(fresh)
            if not fresh:
                return
            values = fresh
        if self.request.latest and len(values) > 1:
            self.overtaken += len(values) - 1
            values = values[-1:]
        self._publish(values)

    def _track_age(self, age: int) -> None:
        self.one_way_ns = moving_average(self.one_way_ns, age)

    def _publish(self, values: list[Any]) -> None:
        """Publish the values of the channel's type; a bad one costs only itself (admission)."""
        try:
            self.values_in += publish_valid(self._convert, self._publisher.publish, values)
        except ValuesRefused as refused:
            self.values_in += refused.published
            self.bad_values += refused.count
            raise

    def health(self, rtt_ns: int) -> dict[str, int]:
        """Per-channel counters for ``Stats`` (names as in client/channels/health.py
        ChannelHealth)."""
        t = self.tracker
        return {"rtt_ns": rtt_ns, "one_way_ns": self.one_way_ns,
                "jitter_ns": self.jitter.jitter_ns if self.values_in else -1, "lost": t.lost,
                "duplicates": t.duplicates, "overwritten": 0,
                "overtaken": self.overtaken + t.stale, "expired": self.expired,
                "values": self.values_in, "rejected": self.bad_values}

    def stats(self) -> dict[str, Any]:
        """Counters for ``rlbridge stats``; ``late`` = duplicates and overtaken values."""
        t = self.tracker
        return {"direction": "publish", "topic": self.request.topic,
                "transport": self.request.transport, "values_in": self.values_in,
                "bad_values": self.bad_values, "malformed": self.malformed,
                "late": t.duplicates + t.stale, "lost": t.lost, "duplicates": t.duplicates,
                "ros_lost": self.ros_lost}

    @property
    def ros_lost(self) -> int:
        """Accepted values the middleware refused to take (never silently: counted here)."""
        return getattr(self._publisher, "failed", 0)

    def close(self) -> None:
        if self.credit is not None:
            self.credit.flow.inbound.pop(self.credit, None)
        self._publisher.close()


class Outbound:
    """Middleware -> client. Numbers values per channel; optionally repeats the last k (UDP)."""

    def __init__(
        self,
        channel: int,
        spec: ValueSpec,
        sink: PacketSink,
        max_batch: int,
        redundancy: int,
        request: TopicConnect,
    ) -> None:
        self.channel = channel
        self.request = request
        self.spec = spec
        self.sink = sink
        self.subscription: Subscription | None = None
        self._max_batch = max_batch
        self._seq = 0
        self._history: deque[tuple[int, Any]] | None = (
            deque(maxlen=redundancy) if redundancy > 0 else None
        )
        self.values_out = 0
        self.dropped = 0
        self.overtaken = 0
        self._latest = request.latest
        self._held: tuple[int, Any] | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._ros_lost = 0
        #: The client's credit and the backlog, for a flow-controlled channel (server/flow.py).
        self.credit: OutboundCredit | None = None

    def on_values(self, values: Sequence[Any], stamp_ns: int | None = None) -> None:
        """Called on the loop thread with a batch from the middleware.

        ``stamp_ns`` is when the middleware delivered the batch (LoopHandoff stamps it on the
        callback's thread); without it, now.
        """
        n = len(values)
        if n == 0:
            return
        stamp = time.time_ns() if stamp_ns is None else stamp_ns
        if self._latest:
            self.overtaken += n - 1 + (self._held is not None)
            self._held = (stamp, values[-1])
            self._release()
            return
        credit = self.credit
        if credit is not None and not credit.passes(self._seq, n):  # else: straight out
            self.dropped += credit.queue(stamp, values)
            self._pump()
            return
        if n == 1 and self._history is None:  # _emit's common case, without the call
            # inlines: Outbound._emit, Outbound._send_run
            seq = self._seq
            self._seq = seq + 1
            self.values_out += 1
            if not self.sink.send(Value(self.channel, seq, stamp, values[0]), data=True):
                self.dropped += 1
            return
        self._emit(stamp, values)

    def on_credit(self, limit: int) -> None:
        """The client consumed values: send what its new credit allows."""
        if self.credit is not None and self.credit.on_credit(limit):
            self._pump()

    def _pump(self) -> None:
        """Send the backlog's oldest values, as many as the client's credit allows, a batch
        at a time while the socket takes them; a full socket is tried again shortly."""
        credit = self.credit
        assert credit is not None
        while True:
            stamps, values = credit.take(self._seq, self._max_batch)
            if not values:
                break
            seq = self._seq
            self._seq = seq + len(values)
            self.values_out += len(values)
            self._send_run(seq, stamps, values)
        if credit.socket_full and credit.waiting and self._timer is None:
            with contextlib.suppress(RuntimeError):  # no loop (a test driving it by hand)
                self._timer = asyncio.get_running_loop().call_later(HOLD_POLL_S,
                                                                    self._on_flow_timer)

    def _on_flow_timer(self) -> None:
        self._timer = None
        self._pump()

    def _release(self) -> None:
        """Write the held latest value, or, while the connection is backed up, poll again."""
        held = self._held
        if held is None:
            return
        if self.sink.congested():
            if self._timer is None:
                try:
                    loop = asyncio.get_running_loop()
                except RuntimeError:  # not on a loop (a test driving it by hand): send now
                    pass
                else:
                    self._timer = loop.call_later(HOLD_POLL_S, self._on_timer)
                    return
            else:
                return
        self._held = None
        self._emit(held[0], [held[1]])

    def _on_timer(self) -> None:
        self._timer = None
        self._release()

    def _emit(self, stamp: int, values: Sequence[Any]) -> None:
        """Number values and send them (with the previous k in front, for redundancy)."""
        n = len(values)
        seq = self._seq
        self._seq = seq + n
        self.values_out += n
        history = self._history
        fresh = list(values)
        values = fresh
        stamps = [stamp] * n
        if history is not None:
            if history:
                # Repeat the previous k values in front: one lost datagram loses no value.
                values = [v for _, v in history] + fresh
                stamps = [s for s, _ in history] + stamps
                seq -= len(history)
            history.extend((stamp, v) for v in fresh)
        self._send_run(seq, stamps, values)

    def _send_run(self, seq: int, stamps: list[int], values: list[Any]) -> None:
        """Values numbered from ``seq`` as Value or Batch packets; refused ones counted.
        With redundancy every packet is a Batch (docs/protocol.md 10.1)."""
        if len(values) == 1 and self._history is None:
            if not self.sink.send(Value(self.channel, seq, stamps[0], values[0]), data=True):
                self.dropped += 1
            return
        step = self._max_batch
        for i in range(0, len(values), step):
            batch = Batch(self.channel, seq + i, stamps[i : i + step], values[i : i + step])
            if not self.sink.send(batch, data=True):
                self.dropped += len(batch.values)

    def health(self, rtt_ns: int) -> dict[str, int]:
        """Per-channel counters for ``Stats``; loss, jitter and age are measured by the client."""
        return {"rtt_ns": rtt_ns, "one_way_ns": -1, "jitter_ns": -1, "lost": -1,
                "duplicates": 0, "overwritten": self.dropped, "overtaken": self.overtaken,
                "expired": 0, "values": self.values_out, "rejected": 0}

    def stats(self) -> dict[str, Any]:
        """Counters for ``rlbridge stats``: values offered to the client, and dropped of those."""
        stats: dict[str, Any] = {
            "direction": "subscribe", "topic": self.request.topic,
            "transport": self.request.transport, "values_out": self.values_out,
            "dropped": self.dropped, "ros_lost": self.ros_lost}
        if self.credit is not None:
            stats["backlog"] = self.credit.waiting
            stats["credit_limit"] = self.credit.limit
        return stats

    @property
    def ros_lost(self) -> int:
        """Messages the middleware lost before the server's subscription took them."""
        return self._ros_lost if self.subscription is None else getattr(
            self.subscription, "lost", 0)

    def close(self) -> None:
        credit = self.credit
        if credit is not None:  # never sent: counted, and the publishers may go on
            self.dropped += credit.clear()
            credit.flow.outbound.discard(credit)
            credit.flow.changed()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._held is not None:  # never sent: counted, not silently lost
            self._held = None
            self.dropped += 1
        discard = getattr(self.sink, "discard", None)  # values waiting for a UDP address
        if discard is not None:  # (server/connect.py ChannelSink): never sent, counted
            discard()
        if self.subscription is not None:
            self._ros_lost = self.ros_lost
            self.subscription.close()
            self.subscription = None
