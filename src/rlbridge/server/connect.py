"""A session's topic-connect requests: which it refuses, and what an accepted one binds.

Refusals are decided before the middleware is asked anything, from the server's limits and the
transports this session has, so a refused request costs no middleware endpoint. An accepted
request becomes an :class:`Inbound` binding (client -> middleware) or an :class:`Outbound` one
(middleware -> client) that sends through its transport's sink as it is at send time.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

from rlbridge.adapters.base import QoS, Reliability
from rlbridge.server.bindings import Inbound, Outbound
from rlbridge.server.flow import SOCKET_SHARE, InboundCredit, OutboundCredit, wants_flow
from rlbridge.server.sinks import PacketSink
from rlbridge.wire import Batch, ErrorCode, Packet, TopicAck, TopicConnect

if TYPE_CHECKING:
    from rlbridge.server.session_owner import SessionOwner

#: Value packets a UDP channel keeps (its newest, at most its QoS depth) while the client's
#: UDP address is unknown: a TCP session's UDP datagram may arrive after its TopicConnect.
HOLD_MAX = 64


def refusal(session: SessionOwner, req: TopicConnect) -> tuple[ErrorCode, str] | None:
    """Why ``session`` may not connect ``req`` (code and reason for its TopicError), or None."""
    cfg = session.ctx.config
    ch = req.channel
    if ch in session.inbound or ch in session.outbound:
        return ErrorCode.CHANNEL_IN_USE, f"channel {ch} is already connected"
    if len(session.inbound) + len(session.outbound) >= cfg.max_channels:
        return ErrorCode.LIMIT, (f"this session already has {cfg.max_channels} channels, "
                                 "the server's limit")
    if req.transport == "tcp" and session.tcp is None:
        return ErrorCode.TRANSPORT_DISABLED, "TCP channel on a session without a TCP connection"
    if req.transport == "udp" and session.ctx.udp_transport is None:
        return ErrorCode.TRANSPORT_DISABLED, "this server runs without UDP (--no-udp)"
    if req.durability == "match" and req.direction == "publish":
        return ErrorCode.BAD_VALUE, ("durability 'match' is for subscribing (it copies the "
                                     "publishers'); publish with 'volatile' or 'transient_local'")
    if len(req.topic) > cfg.max_topic_length:
        return ErrorCode.LIMIT, (f"topic name of {len(req.topic)} characters is longer than "
                                 f"the server's limit of {cfg.max_topic_length}")
    forbidden = session.ctx.access.refusal(session.identity, req.direction, req.topic)
    if forbidden is not None:
        session.ctx.count("topic_not_allowed")
        session.topics_refused += 1
        return ErrorCode.NOT_ALLOWED, forbidden
    return None


def bind(session: SessionOwner, req: TopicConnect) -> Inbound | Outbound:
    """The middleware endpoint of an accepted ``req``; raises ``BindingError`` if it refuses.

    The QoS follows the transport unless the client chose: reliable over TCP, best effort
    over UDP, so the middleware does not retransmit what the client's transport would not.
    Except a latched topic (durability not ``volatile``): reliable on both, because the
    middleware keeps a latched value for reliable readers only (DDS sends a transient-local
    writer's history to late readers by its reliable protocol; a best-effort reader gets the
    next value, which a latched topic may never send), and a reliable reader does not match
    a best-effort writer.
    """
    ctx = session.ctx
    default_rel: Reliability = ("reliable" if req.transport == "tcp"
                                or req.durability != "volatile" else "best_effort")
    qos = QoS(req.reliability or default_rel, req.depth, req.durability)
    adapter = ctx.adapter
    spec = adapter.resolve(req.msg_type, req.field)
    flow = ctx.flows.topic(req.topic) if wants_flow(req) else None
    if req.direction == "publish":
        pub = adapter.create_publisher(req.topic, spec.msg_type, req.field, qos)
        inb = Inbound(req.channel, spec, pub, req, session.link.clock)
        if flow is not None:
            inb.credit = InboundCredit(req.channel, flow, session.send_control)
            flow.inbound[inb.credit] = lambda: inb.tracker.highest + 1
        return inb
    # The transport's sink itself when the session has it (a sink, once made, stays the
    # session's: a new client address is set on it), else one looked up at send time.
    known = session.udp if req.transport == "udp" else session.tcp
    sink = known if known is not None else ChannelSink(session, req.transport,
                                                       min(req.depth, HOLD_MAX))
    out = Outbound(req.channel, spec, sink, ctx.config.max_batch,
                   req.redundancy if req.transport == "udp" else 0, req)

    def on_drop(count: int) -> None:  # batches the loop was too far behind to take
        out.dropped += count

    if isinstance(sink, ChannelSink):  # what it held and could not send counts as dropped
        sink.lost = on_drop

    if flow is not None:  # before subscribing: a latched topic's values use the credit too
        out.credit = OutboundCredit(req.buffer_size, flow,
                                    lambda: getattr(session.tcp, "queued", 0),
                                    ctx.config.max_write_buffer // SOCKET_SHARE)
    parked = out.sink = ParkedSink(sink)  # what subscribing delivers follows the TopicAck
    out.subscription = adapter.subscribe(req.topic, spec.msg_type, req.field, qos,
                                         ctx.handoff.wrap(out.on_values, on_drop))
    if out.credit is not None and flow is not None:
        flow.outbound.add(out.credit)
    if not parked.packets:  # nothing was delivered: no need to wait for the ack
        out.sink = sink
    return out


def acknowledge(session: SessionOwner, binding: Inbound | Outbound,
                via: PacketSink | None) -> None:
    """Send a new binding's TopicAck, then the values its subscription delivered as it was
    made (a latched topic's, parked by :func:`bind`): on one stream the ack comes first."""
    session.send_control(ack_for(binding), via)
    if isinstance(binding, Outbound) and isinstance(binding.sink, ParkedSink):
        parked = binding.sink
        binding.sink = parked.sink
        binding.dropped += parked.release()


class ParkedSink:
    """A subscribe channel's sink while it is being bound: keeps packets, in order, until
    its TopicAck is out (:func:`acknowledge`). Holds at most what the middleware delivers
    while subscribing: a latched topic's values, within the credit if flow-controlled."""

    def __init__(self, sink: PacketSink) -> None:
        self.sink = sink
        self.packets: list[Packet] = []

    @property
    def dropped(self) -> int:
        return 0

    def congested(self) -> bool:
        return False

    def send(self, packet: Packet, *, data: bool = False) -> bool:
        self.packets.append(packet)
        return True

    def release(self) -> int:
        """Send what was kept through the real sink; returns the values it refused."""
        refused = 0
        packets, self.packets = self.packets, []
        for packet in packets:
            if not self.sink.send(packet, data=True):
                refused += len(packet.values) if isinstance(packet, Batch) else 1
        return refused


class ChannelSink:
    """The sink of a channel's chosen transport, looked up at send time.

    A UDP channel may be connected before the client's first datagram told us its address
    (a TCP session's UDP channel: its datagram and its TopicConnect race); the values of that
    time, a latched topic's history among them, wait here (the newest ``hold`` packets) and
    go out once the address is known. A channel whose session has its transport's sink
    already is bound to that sink directly (``bind``): a client's new address (NAT
    rebinding) is set on the sink, which stays the session's.
    """

    def __init__(self, session: SessionOwner, transport: str, hold: int = 0) -> None:
        self._session = session
        self._udp = transport == "udp"
        self._dropped = 0
        self._hold = hold if self._udp else 0
        self._held: deque[Packet] = deque()
        #: Told how many values a packet carried that was held and then not sent.
        self.lost: Callable[[int], None] = lambda count: None

    @property
    def dropped(self) -> int:
        """Packets that found no sink, or a sink that refused them."""
        return self._dropped

    def congested(self) -> bool:
        """True while the transport's sink is backed up (a latest-value channel then waits)."""
        sink = self._session.udp if self._udp else self._session.tcp
        return sink is not None and sink.congested()

    def send(self, packet: Packet, *, data: bool = False) -> bool:
        """Send through the channel's transport as it is now; False (and counted) if not sent."""
        s = self._session
        sink = s.udp if self._udp else s.tcp
        if sink is None:
            if data and self._hold:
                self._keep(packet)
                return True
            self._dropped += 1
            return False
        if self._held:
            self._release()
        if not sink.send(packet, data=data):
            self._dropped += 1
            return False
        return True

    def _keep(self, packet: Packet) -> None:
        held = self._held
        if not held:
            self._session.udp_waiters.append(self._release)
        if len(held) == self._hold:
            self._lose(held.popleft())
        held.append(packet)

    def _release(self) -> None:
        """The client's UDP address is known: send what waited for it, in order."""
        held, self._held = self._held, deque()
        sink = self._session.udp
        for packet in held:
            if sink is None or not sink.send(packet, data=True):
                self._lose(packet)

    def discard(self) -> None:
        """The channel closes: what still waits is never sent, and counted so."""
        held, self._held = self._held, deque()
        for packet in held:
            self._lose(packet)

    def _lose(self, packet: Packet) -> None:
        self._dropped += 1
        self.lost(len(packet.values) if isinstance(packet, Batch) else 1)


def ack_for(binding: Inbound | Outbound) -> TopicAck:
    """A binding's TopicAck: a publish channel's carries the schema its values must match,
    and a flow-controlled one its first credit (server/flow.py)."""
    spec = binding.spec
    if not isinstance(binding, Inbound):
        return TopicAck(binding.channel, spec.msg_type, spec.default)
    credit = binding.credit
    first = None if credit is None else credit.first(binding.tracker.highest + 1)
    return TopicAck(binding.channel, spec.msg_type, spec.default, binding.schema, first)
