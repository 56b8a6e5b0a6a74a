"""One client session: its channels, its watchdog, and the packets it may send and receive.

A session is transport-neutral. A TCP connection or a UDP hello creates it; afterwards packets
reach ``handle`` from either transport (a session may use TCP and UDP channels at once, thesis
requirement 5) and each channel sends through the sink of the transport it chose. Bad input is
answered with an error packet naming the problem and the session goes on; only a broken byte
stream or a dead link ends it.

What may be connected is decided in :mod:`~rlbridge.server.connect`, the liveness timer is
:mod:`~rlbridge.server.watchdog`; this module routes packets and keeps the session's counters.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from functools import partial
from typing import Any

from rlbridge.adapters.base import BindingError
from rlbridge.server.bindings import Inbound, Outbound
from rlbridge.server.connect import ack_for, acknowledge, bind, refusal
from rlbridge.server.context import ServerContext
from rlbridge.server.datagram_limit import refuse_too_large
from rlbridge.server.loss_reports import LossReporter
from rlbridge.server.notices import session_level
from rlbridge.server.ratelimit import RateLimiter
from rlbridge.server.reach import REACH_PACKETS, SessionReach
from rlbridge.server.session_stats import ChannelTotals, stats_reply
from rlbridge.server.sinks import PacketSink, TcpSink, UdpSink
from rlbridge.server.values_in import bundle, value_packet
from rlbridge.server.watchdog import SessionWatchdog
from rlbridge.wire import (
    Batch,
    Bundle,
    Credit,
    Disconnect,
    Error,
    ErrorCode,
    Heartbeat,
    LossReport,
    Packet,
    PacketCodec,
    RemoteProtocolError,
    Stats,
    TopicClose,
    TopicConnect,
    TopicError,
    Value,
)
from rlbridge.wire.codec import PartlyMalformed
from rlbridge.wire.link import LinkMonitor
from rlbridge.wire.seal import SessionKeys

__all__ = ["Session"]

log = logging.getLogger("rlbridge.server")

TOPIC_CONNECT_TAG: int = TopicConnect.__struct_config__.tag  # type: ignore[assignment]


class Session:
    """State and routing for one client; see the module docstring."""

    def __init__(
        self,
        ctx: ServerContext,
        session_id: int,
        token: int,
        name: str,
        on_closed: Callable[[Session], None],
    ) -> None:
        self.ctx = ctx
        self.id = session_id
        self.token = token
        self.name = name
        #: Who the client proved to be: its mutual-TLS certificate's common name, or the name
        #: its own pre-shared key is filed under; None when nothing proved a name
        #: (authorization then applies the default rules: server/authz.py).
        self.identity: str | None = None
        self._on_closed = on_closed
        cfg = ctx.config
        self.link = LinkMonitor(
            time.monotonic_ns(), cfg.heartbeat_ms * 1_000_000, cfg.timeout_ms * 1_000_000
        )
        self.tcp: PacketSink | None = None
        self.udp: UdpSink | None = None
        #: UDP channels holding values until the client's UDP address is known (connect.py).
        self.udp_waiters: list[Callable[[], None]] = []
        self._close_tcp: Callable[[], None] | None = None
        self.inbound: dict[int, Inbound] = {}
        self.outbound: dict[int, Outbound] = {}
        self.packets_in = 0
        self.bytes_in = 0  # added by the transports: whole frames and datagrams
        self.tcp_bytes_in = 0  # of those, on TCP (heartbeats skip a busy TCP connection)
        self.malformed = 0
        self.errors_sent = 0
        #: Topic-connects refused by the key file's rules (server/authz.py).
        self.topics_refused = 0
        #: Totals of channels closed before now, so a session's counters never go back.
        self.totals = ChannelTotals()
        self.closed = False
        #: Seals and opens this session's datagrams (the gate swaps in a SealedCodec).
        self.codec: PacketCodec = ctx.codec
        #: The keys of a pre-shared-key session (the TCP connection seals its records).
        self.keys: SessionKeys | None = None
        self.rate = (None if cfg.max_rate is None
                     else RateLimiter(cfg.max_rate, time.monotonic_ns()))
        self._loss = LossReporter()
        self._watchdog = SessionWatchdog(self)
        #: Services, goals and ROS-side loss reports (server/reach.py).
        self.reach = SessionReach(self)

    # -- transports ------------------------------------------------------------------------
    def attach_tcp(self, sink: PacketSink, close: Callable[[], None]) -> None:
        """The session's TCP connection: its sink, and how to close it when the session ends."""
        self.tcp = sink
        self._close_tcp = close
        if isinstance(sink, TcpSink):
            sink.left_out = self.left_out

    def attach_udp(self, addr: tuple[str, int]) -> None:
        """Learn (or refresh) the client's UDP address from a datagram carrying our token."""
        transport = self.ctx.udp_transport
        if transport is None:
            return
        if self.udp is None:
            cfg = self.ctx.config
            self.udp = UdpSink(transport, self.codec, self.token, addr, cfg.udp_payload,
                               self.ctx.loop, partial(refuse_too_large, self.ctx,
                                                      f"session {self.id} ({self.name})"))
            self.udp.left_out = self.left_out
            waiters, self.udp_waiters = self.udp_waiters, []
            for waiter in waiters:
                waiter()
        elif self.udp.addr != addr:
            self.udp.addr = addr

    def left_out(self, channel: int, count: int) -> None:
        """A sink sent a packet of ``channel`` without ``count`` values, each alone too large
        for the client (a frame, a datagram): counted in the channel's ``dropped``."""
        out = self.outbound.get(channel)
        if out is not None:
            out.dropped += count

    def acknowledged(self) -> None:
        """The ConnectAck is out: the first heartbeat follows it at once (protocol.md 8.1)."""
        if not self.closed:
            self._watchdog.beat()

    @property
    def control(self) -> PacketSink | None:
        """Control replies go over TCP when the session has it, else over UDP."""
        return self.tcp if self.tcp is not None else self.udp

    def send_control(self, packet: Packet, via: PacketSink | None = None) -> None:
        """Send a control packet through ``via``, else the session's control path (if any)."""
        sink = via or self.control
        if sink is not None:
            sink.send(packet)

    def error(self, code: ErrorCode, reason: str, channel: int | None = None,
              via: PacketSink | None = None, values: int = 0) -> None:
        """Tell the client what was wrong with what it sent; the session goes on."""
        self.errors_sent += 1
        self.ctx.count("errors_sent")
        self.ctx.notices.warn(code.name.lower().replace("_", " "),
                              f"session {self.id} ({self.name}): {reason}")
        self.send_control(Error(int(code), reason, channel, values), via)

    def _refuse_channel(self, channel: int, code: ErrorCode, reason: str,
                        via: PacketSink | None) -> None:
        """Answer a topic-connect with its refusal; the operator hears of it (rate-limited)."""
        self.ctx.notices.warn("refused channel", f"session {self.id} ({self.name}): channel "
                              f"{channel} refused: {reason}")
        self.send_control(TopicError(channel, int(code), reason), via)

    # -- packets ---------------------------------------------------------------------------
    def handle(self, packet: Packet, via: str) -> None:
        """Dispatch one packet that arrived on transport ``via`` (``"tcp"`` or ``"udp"``)."""
        if self.closed:
            return
        self.packets_in += 1
        self.link.on_receive(time.monotonic_ns())
        sink = self.tcp if via == "tcp" else self.udp
        if type(packet) is Value:  # nearly every packet: skip the match below
            value_packet(self, packet.channel, packet, sink)
            return
        if type(packet) is Bundle:
            bundle(self, packet, sink)
            return
        match packet:
            case Value(channel=ch) | Batch(channel=ch):
                value_packet(self, ch, packet, sink)
            case Heartbeat():
                self.link.on_heartbeat(packet, time.monotonic_ns(), time.time_ns())
            case Credit(channel=ch):
                out = self.outbound.get(ch)
                if out is None or out.credit is None:
                    self.error(ErrorCode.UNKNOWN_CHANNEL, f"channel {ch} is not a "
                               "flow-controlled subscription; credit ignored", ch, sink)
                else:
                    out.on_credit(packet.limit)
            case TopicConnect():
                self._connect(packet, sink)
            case TopicClose(channel=ch):
                self._close_channel(ch)
            case Stats():
                self._send_stats(sink, packet)
            case _ if isinstance(packet, REACH_PACKETS):
                self.reach.handle(packet, sink)
            case Disconnect():
                self.close("client said goodbye", notify=False)
            case _:
                self.error(ErrorCode.UNEXPECTED,
                           f"a client may not send {type(packet).__name__} here", via=sink)

    def malformed_packet(self, error: RemoteProtocolError, via: PacketSink | None) -> None:
        """Answer a packet that did not decode; a broken topic-connect gets its TopicError.

        A bundle with invalid parts delivers its valid ones, and each invalid part is
        answered as it would be alone.
        """
        if isinstance(error, PartlyMalformed):
            if not self.closed:
                self.packets_in += 1
                self.link.on_receive(time.monotonic_ns())
                bundle(self, error.bundle, via)
            for part in error.errors:
                self.malformed_packet(part, via)
            return
        self.malformed += 1
        self.ctx.count("malformed")
        binding = self.inbound.get(error.channel) if error.channel is not None else None
        if binding is not None:
            binding.malformed += 1
        if error.tag == TOPIC_CONNECT_TAG and error.channel is not None:
            self._refuse_channel(error.channel, ErrorCode.MALFORMED, error.reason, via)
            return
        self.error(ErrorCode.MALFORMED, error.reason, error.channel, via=via)

    def _connect(self, req: TopicConnect, via: PacketSink | None) -> None:
        ch = req.channel
        existing = self.inbound.get(ch) or self.outbound.get(ch)
        if self.reach.owns(ch):
            self.send_control(TopicError(ch, int(ErrorCode.CHANNEL_IN_USE),
                                         f"channel {ch} is already connected"), via)
            return
        if existing is not None and existing.request == req:
            # A retransmitted request (its ack was lost on UDP): answer it again.
            self.send_control(ack_for(existing), via)
            return
        refuse = refusal(self, req)
        if refuse is not None:
            self._refuse_channel(ch, refuse[0], refuse[1], via)
            return
        try:
            binding = bind(self, req)
        except BindingError as exc:
            code = ErrorCode.__members__.get(exc.code, ErrorCode.INTERNAL)
            self._refuse_channel(ch, code, exc.reason, via)
            return
        if isinstance(binding, Inbound):
            self.inbound[ch] = binding
        else:
            self.outbound[ch] = binding
        spec = binding.spec
        log.info("session %d (%s): channel %d %s %s [%s, %s] over %s", self.id, self.name, ch,
                 req.direction, req.topic, spec.msg_type, req.field or "whole", req.transport)
        acknowledge(self, binding, via)

    def report_loss(self) -> None:
        """See :meth:`SessionReach.report_loss` (the watchdog's heartbeat calls it)."""
        self.reach.report_loss()

    def loss_reports(self) -> list[LossReport]:
        """The first hop of every publish channel whose counts moved since the last report.

        Sent by the watchdog every heartbeat period (server/watchdog.py); see
        :mod:`rlbridge.server.loss_reports`.
        """
        return self._loss.reports(self.inbound)

    def _close_channel(self, ch: int) -> None:
        binding: Inbound | Outbound | None = self.inbound.pop(ch, None) or self.outbound.pop(
            ch, None)
        if binding is None:
            if not self.reach.withdraw(ch):
                self.error(ErrorCode.UNKNOWN_CHANNEL, f"channel {ch} is not connected", ch)
            return
        binding.close()  # first: what it drops on closing is in its final counters
        self._retire({**binding.stats(), **binding.health(self.link.rtt_ns)})
        self._loss.forget(ch)
        self.ctx.flows.release(binding.request.topic)

    # -- lifetime --------------------------------------------------------------------------
    def close(self, reason: str, *, notify: bool = True, code: int = 0) -> None:
        """Release every binding and transport; idempotent."""
        if self.closed:
            return
        self.closed = True
        self._watchdog.stop()
        if notify:
            self.send_control(Disconnect(code, reason))
        bindings: list[Inbound | Outbound] = [*self.inbound.values(), *self.outbound.values()]
        for binding in bindings:
            try:
                binding.close()  # first: what it drops on closing is in its final counters
            except Exception:  # a middleware failing to release must not stop the others
                log.exception("closing channel %d of session %d", binding.channel, self.id)
            self._retire({**binding.stats(), **binding.health(self.link.rtt_ns)})
            self.ctx.flows.release(binding.request.topic)
        self.inbound.clear()
        self.outbound.clear()
        self.reach.close()
        if self._close_tcp is not None:
            self._close_tcp()
        log.log(session_level(self.name), "session %d (%s) closed: %s", self.id, self.name,
                reason)
        self._on_closed(self)

    # -- counters --------------------------------------------------------------------------
    def _send_stats(self, sink: PacketSink | None, ask: Stats | None = None) -> None:
        reply = stats_reply(self.ctx, self.stats(), over_tcp=sink is not None and sink is self.tcp,
                            sees_all=self.ctx.access.sees_all(self.identity),
                            services=ask is not None and bool(ask.body.get("services")))
        self.send_control(reply, sink)

    def _retire(self, channel: dict[str, Any]) -> None:
        self.totals.retire(channel)
        self.ctx.ledger.retire_channel(self.name, channel)

    def channel_stats(self) -> dict[str, dict[str, Any]]:
        """One dict per channel id (as a string: JSON keys); other counters go into these."""
        rtt = self.link.rtt_ns
        return {**{str(c): {**b.stats(), **b.health(rtt)} for c, b in self.inbound.items()},
                **{str(c): {**b.stats(), **b.health(rtt)} for c, b in self.outbound.items()},
                **self.reach.channel_stats()}

    def stats(self) -> dict[str, Any]:
        """This session's counters; value totals include channels already closed."""
        now = time.monotonic_ns()
        link = self.link.stats(now)
        channels = self.channel_stats()
        totals = self.totals.totals(channels)
        return {
            "session": self.id,
            "name": self.name,
            "identity": self.identity,
            "state": link.state.value,
            "rtt_us": link.rtt_ns / 1000 if link.rtt_ns >= 0 else None,
            "packets_in": self.packets_in,
            "bytes_in": self.bytes_in,
            "bytes_out": sum(getattr(s, "bytes_out", 0) for s in {self.tcp, self.udp} if s),
            "tcp_queued_bytes": getattr(self.tcp, "queued", 0),
            "malformed": self.malformed,
            "errors_sent": self.errors_sent,
            "topics_refused": self.topics_refused,
            **totals,
            **self.reach.stats(),
            "channels": channels,
        }

