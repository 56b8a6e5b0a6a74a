"""The UDP endpoint: datagrams to sessions by token, never by source address alone."""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from typing import cast

from rlbridge.server.config import UDP_RECEIVE_BUFFER
from rlbridge.server.gate import Gate
from rlbridge.server.notices import peer_address, session_level
from rlbridge.server.registry import SessionRegistry
from rlbridge.server.session import Session
from rlbridge.server.sinks import UdpSink
from rlbridge.sockbuf import BufferGrant, request_buffer
from rlbridge.wire import (
    PROTOCOL_VERSION,
    AuthProof,
    ConnectError,
    Disconnect,
    Hello,
    Packet,
    PacketCodec,
    RemoteProtocolError,
)
from rlbridge.wire.auth import SEAL_OVERHEAD, DatagramRejected, ServerHandshake
from rlbridge.wire.codec import (
    DATAGRAM_HEADER,
    FLAG_BUNDLES,
    FLAG_MAC,
    MAGIC,
    check_header,
    peek_header,
)

log = logging.getLogger("rlbridge.server")

#: UDP handshakes (challenge sent, proof awaited) remembered at once; beyond, oldest go.
MAX_PENDING = 256
#: What every datagram of this protocol version starts with: magic and version.
HEADER_PREFIX = MAGIC + bytes((PROTOCOL_VERSION,))


class UdpEndpoint(asyncio.DatagramProtocol):
    """One socket for every UDP client.

    A datagram with token 0 may only be a hello: it creates a UDP-only session (thesis 4.1.1)
    and the reply carries the token. Any other datagram must carry a live token; its source
    address becomes the session's UDP address (also how a TCP session starts using UDP
    channels). Datagrams with unknown tokens are dropped and counted, never answered, so the
    endpoint cannot be used to reflect traffic at a third party. With keys, the hello is
    answered with a challenge, kept per source address until its proof arrives, and every
    later datagram must carry a valid MAC and a fresh counter (:mod:`rlbridge.wire.auth`).
    """

    def __init__(self, registry: SessionRegistry) -> None:
        self._registry = registry
        self._transport: asyncio.DatagramTransport | None = None
        # A retransmitted hello (its ack was lost) gets the same session, not a second one.
        self._hello_sessions: dict[tuple[tuple[str, int], str], tuple[int, Hello]] = {}
        self._gate = Gate(registry)
        self._pending: dict[tuple[str, int], _Pending] = {}
        #: What the kernel granted the socket's receive buffer (``udp_receive_buffer``).
        self.receive_buffer: BufferGrant | None = None
        registry.on_forget.append(lambda s: self.forget(s.id))
        #: Set when the transport has really closed; shutdown waits for it, else the loop
        #: can end first and the socket is reaped by the garbage collector (ResourceWarning).
        self.closed = asyncio.Event()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = cast(asyncio.DatagramTransport, transport)
        self._registry.ctx.udp_transport = self._transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            # Every client's datagrams queue here while the loop is busy; the default buffer
            # (~200 KiB, under 200 small datagrams) drops a single client's burst. What the
            # kernel granted is logged after the listening line (rlbridge.sockbuf).
            self.receive_buffer = request_buffer(
                sock, "receive", self._registry.ctx.config.udp_receive_buffer or UDP_RECEIVE_BUFFER)

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed.set()

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        ctx = self._registry.ctx
        # ``networks``, not ``bool(allow)``: this runs per datagram and a Python-level
        # ``__bool__`` is a call; same test.
        if ctx.allow.networks and not ctx.allow.allows(addr[0]):
            ctx.count("udp_not_allowed")
            return
        # The checks in the order docs/protocol.md section 3 gives them; none is answered
        # before the token has picked a live session.
        if len(data) < DATAGRAM_HEADER.size or data[:3] != HEADER_PREFIX:
            ctx.count("udp_malformed")  # not ours, or not this version: nobody to tell
            ctx.notices.warn("malformed", f"malformed UDP datagram from {addr}: "
                             f"{_header_fault(data)}")
            return
        flags, token = peek_header(data)
        seal = SEAL_OVERHEAD if flags & FLAG_MAC else 0
        if len(data) - DATAGRAM_HEADER.size - seal > ctx.config.max_packet:
            ctx.count("udp_too_large")
            return
        session = self._registry.by_token(token) if token else None
        if token and session is None:
            ctx.count("udp_bad_token")  # a session that is gone, or a guess: never decoded
            return
        # The token picks the session, and the session the codec: an authenticated session's
        # datagrams must verify under its keys before their body is even decoded.
        codec = session.codec if session is not None else ctx.codec
        # The hot path (a live session, no keys): the header is checked already, so decode
        # only the body, what decode_datagram would do next (one call, not three).
        plain = session is not None and type(codec) is PacketCodec
        try:
            if plain:
                packet = codec.decode_body(memoryview(data)[DATAGRAM_HEADER.size :])
            else:
                flags, token, packet = codec.decode_datagram(data)
        except DatagramRejected as rejected:  # its own name: mypyc types a name by its first use
            ctx.count(f"udp_{rejected.kind}")  # forged, replayed or unsealed: never answered
            ctx.notices.warn("rejected datagram", f"dropped a UDP datagram from {addr}: "
                             f"{rejected.reason}")
            return
        except RemoteProtocolError as exc:
            if plain:
                exc.token = token  # as decode_datagram sets it
            ctx.count("udp_malformed")
            ctx.notices.warn("malformed", f"malformed UDP datagram from {addr}: {exc.reason}")
            # A live token (verified, if the session has keys) proves the sender is the
            # client: tell it what was wrong, at the address it registered.
            if session is not None and session.udp is not None:
                session.malformed_packet(exc, session.udp)
            return
        if session is None:
            if isinstance(packet, Hello):
                self._hello(packet, addr)
            elif isinstance(packet, AuthProof):
                self._proof(packet, addr)
            elif isinstance(packet, Disconnect) and self._unproven(addr):
                self._gate.abandoned(packet, self._pending[addr].hello, peer_address(addr))
                del self._pending[addr]
            else:
                ctx.count("udp_no_token")
            return
        session.bytes_in += len(data)
        udp = session.udp
        if udp is None or udp.addr != addr:  # attach_udp's own test, without the call
            session.attach_udp(addr)
            udp = session.udp
        if flags & FLAG_BUNDLES and udp is not None and not udp.bundles:
            udp.bundles = True  # the client reads bundles: cork and bundle its values
        session.handle(packet, "udp")

    def _hello(self, hello: Hello, addr: tuple[str, int]) -> None:
        known = self._hello_sessions.get((addr, hello.name))
        if known is not None and known[1] == hello:  # a retransmitted hello: same session
            session = self._live(known[0])
            if session is not None:
                self._acknowledge(session, addr)
                return
        pending = self._pending.get(addr)
        if pending is not None and pending.hello == hello:  # its challenge was lost
            self._send(pending.handshake.challenge, addr)
            return
        result = self._gate.hello(hello, peer_address(addr), udp=True)
        if isinstance(result, ServerHandshake):
            self._pending.pop(addr, None)
            self._pending[addr] = _Pending(hello, result)
            while len(self._pending) > MAX_PENDING:  # spoofed hellos evict the oldest
                del self._pending[next(iter(self._pending))]
                self._registry.ctx.count("udp_handshakes_evicted")
            self._send(result.challenge, addr)
        else:
            self._opened(hello, result, addr)

    def _proof(self, proof: AuthProof, addr: tuple[str, int]) -> None:
        pending = self._pending.get(addr)
        if pending is None:  # no challenge outstanding: a stray or replayed proof
            self._registry.ctx.count("udp_unexpected_proof")
            return
        if pending.session_id is not None:
            # Proved already: the same proof again means our ack was lost; anything else is
            # refused like any wrong proof would be.
            session = self._live(pending.session_id)
            if proof == pending.proof and session is not None:
                self._acknowledge(session, addr)
            else:
                self._registry.ctx.count("udp_unexpected_proof")
            return
        result = self._gate.finish(pending.handshake, pending.hello, proof, peer_address(addr))
        if isinstance(result, Session):
            pending.session_id, pending.proof = result.id, proof
        else:
            del self._pending[addr]
        self._opened(pending.hello, result, addr)

    def _unproven(self, addr: tuple[str, int]) -> bool:
        pending = self._pending.get(addr)
        return pending is not None and pending.session_id is None

    def _live(self, session_id: int) -> Session | None:
        return next((s for s in self._registry if s.id == session_id and not s.closed), None)

    def _opened(self, hello: Hello, result: Session | ConnectError,
                addr: tuple[str, int]) -> None:
        if isinstance(result, ConnectError):
            self._send(result, addr)
            return
        self._hello_sessions[(addr, hello.name)] = (result.id, hello)
        log.log(session_level(hello.name), "session %d (%s) opened over UDP from %s", result.id,
                hello.name, addr)
        self._acknowledge(result, addr)

    def _acknowledge(self, session: Session, addr: tuple[str, int]) -> None:
        session.attach_udp(addr)
        sink = session.udp
        assert isinstance(sink, UdpSink)
        sink.send(self._registry.ack(session))
        session.acknowledged()  # the first heartbeat; none for a retransmitted hello's ack

    def _send(self, packet: Packet, addr: tuple[str, int]) -> None:
        assert self._transport is not None
        self._transport.sendto(self._registry.ctx.codec.encode_datagram(packet, 0), addr)

    def forget(self, session_id: int) -> None:
        for key, (sid, _hello) in list(self._hello_sessions.items()):
            if sid == session_id:
                del self._hello_sessions[key]
        for addr, pending in list(self._pending.items()):
            if pending.session_id == session_id:
                del self._pending[addr]


@dataclass
class _Pending:
    """A UDP key handshake: challenge sent; after the proof, the session it opened."""

    hello: Hello
    handshake: ServerHandshake
    session_id: int | None = None
    proof: AuthProof | None = None


def _header_fault(data: bytes) -> str:
    """Why a datagram's header is not ours, for the operator (off the hot path)."""
    if len(data) < DATAGRAM_HEADER.size:
        return f"{len(data)} bytes, shorter than the {DATAGRAM_HEADER.size}-byte header"
    magic, version = data[:2], data[2]
    try:
        check_header(magic, version)
    except RemoteProtocolError as exc:
        return exc.reason
    return "bad header"
