"""One client session: its channels, its watchdog, and the packets it may send and receive.

A session is transport-neutral. A TCP connection or a UDP hello creates it; afterwards packets
reach ``handle`` from either transport (a session may use TCP and UDP channels at once, thesis
requirement 5) and each channel sends through the sink of the transport it chose. Bad input is
answered with an error packet naming the problem and the session goes on; only a broken byte
stream or a dead link ends it.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import msgspec

from rlbridge.adapters.base import BindingError, MiddlewareAdapter, QoS, Reliability
from rlbridge.server.access import AllowList, KeyStore
from rlbridge.server.bindings import Inbound, Outbound
from rlbridge.server.config import ServerConfig
from rlbridge.server.handoff import LoopHandoff
from rlbridge.server.ratelimit import RateLimiter
from rlbridge.server.sinks import PacketSink, UdpSink
from rlbridge.wire import (
    Batch,
    Disconnect,
    Error,
    ErrorCode,
    Heartbeat,
    Packet,
    PacketCodec,
    RemoteProtocolError,
    Stats,
    TopicAck,
    TopicClose,
    TopicConnect,
    TopicError,
    Value,
)
from rlbridge.wire.link import LinkMonitor, LinkState

log = logging.getLogger("rlbridge.server")

#: Per-channel counters a session (and the server) also reports as totals.
CHANNEL_TOTALS = ("values_in", "values_out", "dropped", "late", "bad_values")

TOPIC_CONNECT_TAG: int = TopicConnect.__struct_config__.tag  # type: ignore[assignment]


@dataclass
class ServerContext:
    """What every session shares: settings, middleware, codec, the loop and its hand-off."""

    config: ServerConfig
    adapter: MiddlewareAdapter
    codec: PacketCodec
    loop: asyncio.AbstractEventLoop
    handoff: LoopHandoff
    udp_transport: asyncio.DatagramTransport | None = None
    counters: dict[str, int] = field(default_factory=dict)
    keys: KeyStore | None = None
    #: TCP connections still in their hello/handshake (no session yet): closed at shutdown.
    handshaking: set[asyncio.BaseTransport] = field(default_factory=set)
    allow: AllowList = field(default_factory=lambda: AllowList(()))
    #: Server totals and every session's counters (set by the registry; see ``Stats``).
    report: Callable[[], dict[str, Any]] | None = None

    def count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n


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
        self._on_closed = on_closed
        cfg = ctx.config
        self.link = LinkMonitor(
            time.monotonic_ns(), cfg.heartbeat_ms * 1_000_000, cfg.timeout_ms * 1_000_000
        )
        self.tcp: PacketSink | None = None
        self.udp: UdpSink | None = None
        self._close_tcp: Callable[[], None] | None = None
        self.inbound: dict[int, Inbound] = {}
        self.outbound: dict[int, Outbound] = {}
        self.packets_in = 0
        self.bytes_in = 0  # added by the transports: whole frames and datagrams
        self.tcp_bytes_in = 0  # of those, on TCP (heartbeats skip a busy TCP connection)
        self.malformed = 0
        self.errors_sent = 0
        #: Totals of channels closed before now, so a session's counters never go back.
        self._retired: dict[str, int] = dict.fromkeys(CHANNEL_TOTALS, 0)
        self.closed = False
        #: Seals and opens this session's datagrams (the gate swaps in a SealedCodec).
        self.codec: PacketCodec = ctx.codec
        self.rate = (None if cfg.max_rate is None
                     else RateLimiter(cfg.max_rate, time.monotonic_ns()))
        self._timer: asyncio.TimerHandle | None = None
        self._tcp_bytes_at_heartbeat = (-1, -1)
        self._arm_timer()

    # -- transports ------------------------------------------------------------------------
    def attach_tcp(self, sink: PacketSink, close: Callable[[], None]) -> None:
        self.tcp = sink
        self._close_tcp = close

    def attach_udp(self, addr: tuple[str, int]) -> None:
        """Learn (or refresh) the client's UDP address from a datagram carrying our token."""
        transport = self.ctx.udp_transport
        if transport is None:
            return
        if self.udp is None:
            cfg = self.ctx.config
            self.udp = UdpSink(transport, self.codec, self.token, addr, cfg.udp_payload)
        elif self.udp.addr != addr:
            self.udp.addr = addr

    @property
    def control(self) -> PacketSink | None:
        """Control replies go over TCP when the session has it, else over UDP."""
        return self.tcp if self.tcp is not None else self.udp

    def send_control(self, packet: Packet, via: PacketSink | None = None) -> None:
        sink = via or self.control
        if sink is not None:
            sink.send(packet)

    def error(self, code: ErrorCode, reason: str, channel: int | None = None,
              via: PacketSink | None = None) -> None:
        """Tell the client what was wrong with what it sent; the session goes on."""
        self.errors_sent += 1
        self.ctx.count("errors_sent")
        log.debug("session %d (%s): %s: %s", self.id, self.name, code.name, reason)
        self.send_control(Error(int(code), reason, channel), via)

    # -- packets ---------------------------------------------------------------------------
    def handle(self, packet: Packet, via: str) -> None:
        """Dispatch one packet that arrived on transport ``via`` (``"tcp"`` or ``"udp"``)."""
        if self.closed:
            return
        self.packets_in += 1
        self.link.on_receive(time.monotonic_ns())
        sink = self.tcp if via == "tcp" else self.udp
        if type(packet) is Value:  # nearly every packet: skip the match below
            self._data(packet.channel, packet, sink)
            return
        match packet:
            case Value(channel=ch):
                self._data(ch, packet, sink)
            case Batch(channel=ch):
                self._data(ch, packet, sink)
            case Heartbeat():
                self.link.on_heartbeat(packet, time.monotonic_ns(), time.time_ns())
            case TopicConnect():
                self._connect(packet, sink)
            case TopicClose(channel=ch):
                self._close_channel(ch)
            case Stats():
                self._send_stats(sink)
            case Disconnect():
                self.close("client said goodbye", notify=False)
            case _:
                self.error(ErrorCode.UNEXPECTED,
                           f"a client may not send {type(packet).__name__} here", via=sink)

    def malformed_packet(self, error: RemoteProtocolError, via: PacketSink | None) -> None:
        """Answer a packet that did not decode; a broken topic-connect gets its TopicError."""
        self.malformed += 1
        self.ctx.count("malformed")
        binding = self.inbound.get(error.channel) if error.channel is not None else None
        if binding is not None:
            binding.malformed += 1
        if error.tag == TOPIC_CONNECT_TAG and error.channel is not None:
            self.send_control(TopicError(error.channel, int(ErrorCode.MALFORMED), error.reason),
                              via)
            return
        self.error(ErrorCode.MALFORMED, error.reason, error.channel, via=via)

    def _data(self, channel: int, packet: Value | Batch, via: PacketSink | None) -> None:
        binding = self.inbound.get(channel)
        if binding is None:
            n = 1 if isinstance(packet, Value) else len(packet.values)
            self._retired["dropped"] += n
            self.ctx.count("dropped_unknown_channel", n)
            code = ErrorCode.UNKNOWN_CHANNEL
            what = "is bound for subscribing" if channel in self.outbound else "is not connected"
            self.error(code, f"channel {channel} {what}; cannot publish on it", channel, via)
            return
        if self.rate is not None:
            admitted = self._limit(packet, via)
            if admitted is None:
                return
            packet = admitted
        try:
            if isinstance(packet, Value):
                binding.on_value(packet)
            else:
                binding.on_batch(packet)
        except msgspec.ValidationError as exc:
            self.error(ErrorCode.BAD_VALUE,
                       f"channel {channel} ({binding.spec.msg_type} field "
                       f"{binding.spec.field or '<whole message>'}): {exc}", channel, via)

    def _limit(self, packet: Value | Batch, via: PacketSink | None) -> Value | Batch | None:
        """The values ``--max-rate`` lets through (a batch's first ones); the rest counted."""
        assert self.rate is not None
        now = time.monotonic_ns()
        n = 1 if isinstance(packet, Value) else len(packet.values)
        ok = self.rate.admit(n, now)
        if ok < n:
            self.ctx.count("rate_dropped", n - ok)
            if self.rate.should_warn(now):
                self.error(ErrorCode.LIMIT, f"over the server's limit of {self.rate.rate:g} "
                           f"values per second per session; {self.rate.dropped} values dropped "
                           "so far", packet.channel, via)
        if ok == n:
            return packet
        if ok == 0 or isinstance(packet, Value):
            return None
        return Batch(packet.channel, packet.first_seq, packet.stamps[:ok], packet.values[:ok])

    def _connect(self, req: TopicConnect, via: PacketSink | None) -> None:
        cfg = self.ctx.config
        ch = req.channel
        refuse: tuple[ErrorCode, str] | None = None
        existing = self.inbound.get(ch) or self.outbound.get(ch)
        if existing is not None and existing.request == req:
            # A retransmitted request (its ack was lost on UDP): answer it again.
            self.send_control(TopicAck(ch, existing.spec.msg_type, existing.spec.default), via)
            return
        if existing is not None:
            refuse = (ErrorCode.CHANNEL_IN_USE, f"channel {ch} is already connected")
        elif len(self.inbound) + len(self.outbound) >= cfg.max_channels:
            refuse = (ErrorCode.LIMIT, f"this session already has {cfg.max_channels} channels, "
                      "the server's limit")
        elif req.transport == "tcp" and self.tcp is None:
            refuse = (ErrorCode.TRANSPORT_DISABLED,
                      "TCP channel on a session without a TCP connection")
        elif req.transport == "udp" and self.ctx.udp_transport is None:
            refuse = (ErrorCode.TRANSPORT_DISABLED, "this server runs without UDP (--no-udp)")
        elif len(req.topic) > cfg.max_topic_length:
            refuse = (ErrorCode.LIMIT, f"topic name of {len(req.topic)} characters is longer "
                      f"than the server's limit of {cfg.max_topic_length}")
        if refuse is not None:
            self.send_control(TopicError(ch, int(refuse[0]), refuse[1]), via)
            return
        default_rel: Reliability = "reliable" if req.transport == "tcp" else "best_effort"
        qos = QoS(req.reliability or default_rel, req.depth)
        adapter = self.ctx.adapter
        try:
            spec = adapter.resolve(req.msg_type, req.field)
            if req.direction == "publish":
                pub = adapter.create_publisher(req.topic, spec.msg_type, req.field, qos)
                self.inbound[ch] = Inbound(ch, spec, pub, req, self.link.clock)
            else:
                out = Outbound(ch, spec, _ChannelSink(self, req.transport), cfg.max_batch,
                               req.redundancy if req.transport == "udp" else 0, req)
                out.subscription = adapter.subscribe(
                    req.topic, spec.msg_type, req.field, qos, self.ctx.handoff.wrap(out.on_values)
                )
                self.outbound[ch] = out
        except BindingError as exc:
            code = ErrorCode.__members__.get(exc.code, ErrorCode.INTERNAL)
            self.send_control(TopicError(ch, int(code), exc.reason), via)
            return
        log.info("session %d (%s): channel %d %s %s [%s, %s] over %s", self.id, self.name, ch,
                 req.direction, req.topic, spec.msg_type, req.field or "whole", req.transport)
        self.send_control(TopicAck(ch, spec.msg_type, spec.default), via)

    def _close_channel(self, ch: int) -> None:
        binding: Inbound | Outbound | None = self.inbound.pop(ch, None) or self.outbound.pop(
            ch, None)
        if binding is None:
            self.error(ErrorCode.UNKNOWN_CHANNEL, f"channel {ch} is not connected", ch)
            return
        self._retire(binding.stats())
        binding.close()

    # -- watchdog --------------------------------------------------------------------------
    def _arm_timer(self) -> None:
        now = time.monotonic_ns()
        deadline = self.link.next_deadline(now)
        loop = self.ctx.loop
        self._timer = loop.call_at(loop.time() + (deadline - now) / 1e9, self._on_timer)

    def _on_timer(self) -> None:
        if self.closed:
            return
        now = time.monotonic_ns()
        if self.link.state(now) is LinkState.LOST:
            self.ctx.count("sessions_timed_out")
            self.close("watchdog: no packet from the client within "
                       f"{self.ctx.config.timeout_ms} ms", notify=True)
            return
        if self.link.heartbeat_due(now):
            hb = self.link.make_heartbeat(now, time.time_ns())
            for sink in self._heartbeat_sinks():
                sink.send(hb)
            self._tcp_bytes_at_heartbeat = self._tcp_traffic()
        self._arm_timer()

    def _tcp_traffic(self) -> tuple[int, int]:
        return getattr(self.tcp, "bytes_out", -1), self.tcp_bytes_in

    def _heartbeat_sinks(self) -> list[PacketSink]:
        """Both transports, but not a TCP connection that carried data either way since the
        last heartbeat while the client also has UDP (where heartbeats keep flowing): a
        heartbeat segment amid a stream makes the receiver's kernel delay its ACKs (it
        expects to piggyback them), and with Nagle on the sender then holds the next value
        for that delayed ACK, ~40 ms every heartbeat period (docs/evaluation.md)."""
        tcp, udp = self.tcp, self.udp
        if tcp is None or udp is None:
            return [s for s in (tcp, udp) if s is not None]
        if self._tcp_traffic() != self._tcp_bytes_at_heartbeat:
            return [udp]
        return [tcp, udp]

    # -- lifetime --------------------------------------------------------------------------
    def close(self, reason: str, *, notify: bool = True, code: int = 0) -> None:
        """Release every binding and transport; idempotent."""
        if self.closed:
            return
        self.closed = True
        if self._timer is not None:
            self._timer.cancel()
        if notify:
            self.send_control(Disconnect(code, reason))
        bindings: list[Inbound | Outbound] = [*self.inbound.values(), *self.outbound.values()]
        for binding in bindings:
            self._retire(binding.stats())
            try:
                binding.close()
            except Exception:  # a middleware failing to release must not stop the others
                log.exception("closing channel %d of session %d", binding.channel, self.id)
        self.inbound.clear()
        self.outbound.clear()
        if self._close_tcp is not None:
            self._close_tcp()
        log.info("session %d (%s) closed: %s", self.id, self.name, reason)
        self._on_closed(self)

    # -- counters --------------------------------------------------------------------------
    def _send_stats(self, sink: PacketSink | None) -> None:
        """Answer ``Stats``: this session, and over TCP every session and the server totals.

        A datagram cannot hold a thousand channels' counters, so a UDP control path gets this
        session's counters and the server's counters only.
        """
        body: dict[str, Any] = {"session": self.stats(), "server": dict(self.ctx.counters),
                                "topics": [list(t) for t in self.ctx.adapter.topics()]}
        if self.ctx.report is not None:
            report = self.ctx.report()
            body["server"] = report["server"]
            if sink is not None and sink is self.tcp:
                body["sessions"] = report["sessions"]
        self.send_control(Stats(body), sink)

    def _retire(self, channel: dict[str, Any]) -> None:
        for key in CHANNEL_TOTALS:
            self._retired[key] += channel.get(key, 0)

    def channel_stats(self) -> dict[str, dict[str, Any]]:
        """One dict per channel id (as a string: JSON keys); other counters go into these."""
        rtt = self.link.rtt_ns
        return {**{str(c): {**b.stats(), **b.health(rtt)} for c, b in self.inbound.items()},
                **{str(c): {**b.stats(), **b.health(rtt)} for c, b in self.outbound.items()}}

    def stats(self) -> dict[str, Any]:
        """This session's counters; value totals include channels already closed."""
        now = time.monotonic_ns()
        link = self.link.stats(now)
        channels = self.channel_stats()
        totals = dict(self._retired)
        for channel in channels.values():
            for key in CHANNEL_TOTALS:
                totals[key] += channel.get(key, 0)
        return {
            "session": self.id,
            "name": self.name,
            "state": link.state.value,
            "rtt_us": link.rtt_ns / 1000 if link.rtt_ns >= 0 else None,
            "packets_in": self.packets_in,
            "bytes_in": self.bytes_in,
            "bytes_out": sum(getattr(s, "bytes_out", 0) for s in {self.tcp, self.udp} if s),
            "tcp_queued_bytes": getattr(self.tcp, "queued", 0),
            "malformed": self.malformed,
            "errors_sent": self.errors_sent,
            **totals,
            "channels": channels,
        }


class _ChannelSink:
    """The sink of a channel's chosen transport, looked up at send time.

    A UDP channel may be connected before the client's first datagram told us its address, and
    a client's address may change (NAT rebinding); looking the sink up per send handles both.
    """

    def __init__(self, session: Session, transport: str) -> None:
        self._session = session
        self._udp = transport == "udp"
        self._dropped = 0

    @property
    def dropped(self) -> int:
        return self._dropped

    def congested(self) -> bool:
        sink = self._session.udp if self._udp else self._session.tcp
        return sink is not None and sink.congested()

    def send(self, packet: Packet, *, data: bool = False) -> bool:
        s = self._session
        sink = s.udp if self._udp else s.tcp
        if sink is None or not sink.send(packet, data=data):
            self._dropped += 1
            return False
        return True
