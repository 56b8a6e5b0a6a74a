"""The TCP listener's per-connection protocol: bytes to packets to the session, and back."""

from __future__ import annotations

import asyncio
import logging
import os
import socket
from typing import cast

from rlbridge.server.gate import Gate
from rlbridge.server.guarded import GuardedTransport
from rlbridge.server.notices import peer_address, session_level
from rlbridge.server.registry import SessionRegistry
from rlbridge.server.session import Session
from rlbridge.server.sinks import TcpSink
from rlbridge.server.tls_side import ServerTls
from rlbridge.wire import (
    AuthProof,
    Batch,
    Bundle,
    ConnectError,
    Disconnect,
    Error,
    ErrorCode,
    FrameDecoder,
    Hello,
    Malformed,
    Packet,
    PacketCodec,
    RemoteProtocolError,
    Value,
)
from rlbridge.wire.auth import ServerHandshake
from rlbridge.wire.records import RecordOpener, SealedStreamDecoder, stream_sealers
from rlbridge.wire.seal import KEY_SIZE, sealed_codec, tls_datagram_keys

log = logging.getLogger("rlbridge.server")

#: A read at least this large yields the loop before the connection is read again.
YIELD_AFTER_BYTES = 64 << 10
#: Seconds a new connection has to complete its hello (and proof) before it is closed.
HELLO_TIMEOUT = 10.0


def _values(session: Session, run: list[Value | Batch]) -> None:
    """Consecutive value frames of one read to the session (``TcpConnection._to_session``)."""
    if len(run) == 1:
        session.handle(run[0], "tcp")
    elif not session.closed:
        session.handle(Bundle(run), "tcp")
        session.packets_in += len(run) - 1  # one per frame, as if each had come alone


class TcpConnection(asyncio.Protocol):
    """One client socket. The first packet must be a hello; then everything goes to its session.

    Packets are decoded whole as soon as their last byte arrives (``data_received``), and every
    value in them is delivered before the next read: nothing polls (thesis 3.2.2). A header
    that loses the framing is answered after the packets before it in the same read have
    been handled, so what the server does never depends on how the stream was cut into reads.
    """

    def __init__(self, registry: SessionRegistry) -> None:
        self._registry = registry
        ctx = registry.ctx
        self._decoder: FrameDecoder | SealedStreamDecoder = FrameDecoder(
            ctx.codec, ctx.config.max_packet)
        self._transport: asyncio.Transport | None = None
        self._sink: TcpSink | None = None
        self._session: Session | None = None
        self._peer = "?"
        self._gate = Gate(registry)
        #: The hello and its handshake while a key-requiring server waits for the proof.
        self._pending: tuple[Hello, ServerHandshake] | None = None
        #: A hello arrived, or the server closed the connection saying why: its end needs no
        #: further word (else a TLS client that hung up is logged: ServerTls.hung_up).
        self._explained = False
        self._deadline: asyncio.TimerHandle | None = None
        self._tls: ServerTls | None = None
        self._guarded: GuardedTransport | None = None
        #: Set when the keys were installed mid-read: records after the proof then wait in
        #: the decoder and are read at the end of this ``data_received``.
        self._refeed = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = t = cast(asyncio.Transport, transport)
        ctx = self._registry.ctx
        self._peer = peer_address(t.get_extra_info("peername"))
        sock = t.get_extra_info("socket")
        if sock is not None:
            # Set either way: asyncio and uvloop turn Nagle off on every TCP transport, so
            # without --nodelay it has to be turned back on to mean what the option says.
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, int(ctx.config.nodelay))
        t.set_write_buffer_limits(high=ctx.config.max_write_buffer)
        peer = t.get_extra_info("peername")
        refused = self._gate.allowed(peer[0] if peer else "?", "TCP connection")
        if refused is not None:  # in plain protocol, before any TLS: nothing to protect
            TcpSink(t, ctx.codec, ctx.config.max_write_buffer).send(refused)
            t.close()
            return
        out: asyncio.Transport = t
        if ctx.tls is not None:
            self._tls = ServerTls(ctx.tls, t, ctx, self._peer)
            out = self._tls.transport
        elif ctx.keys is not None:
            # Plain frames until the proof, sealed records after (wire/records.py).
            self._guarded = out = GuardedTransport(t, GuardedTransport.plain)
            self._decoder = SealedStreamDecoder(ctx.codec, ctx.config.max_packet,
                                                stop_after=AuthProof)
        self._sink = TcpSink(out, ctx.codec, ctx.config.max_write_buffer, ctx.loop)
        # A connection that never completes its hello (or its proof) must not hold a socket.
        self._deadline = ctx.loop.call_later(HELLO_TIMEOUT, self._no_hello)
        ctx.handshaking.add(t)

    def data_received(self, data: bytes) -> None:
        if self._sink is None:  # refused at connect (allow-list): nothing more is read
            return
        if len(data) >= YIELD_AFTER_BYTES and self._transport is not None:
            # Fairness: uvloop (libuv) reads a busy socket up to 32 times in one loop
            # iteration; a flooding client would hold the loop for seconds, starving other
            # sessions, the corked writes and the watchdog (which then drops clients whose
            # heartbeats sit unread). Pause after a large chunk, resume on the next iteration.
            self._transport.pause_reading()
            self._registry.ctx.loop.call_soon(self._resume_reading)
        if self._tls is not None:
            plain = self._tls.received(data)
            if not plain:
                return
            data = plain
        packets, fault = self._decoder.feed_until_fault(data)
        session = self._session
        if session is not None:
            session.bytes_in += len(data)
            session.tcp_bytes_in += len(data)
            self._to_session(session, packets)
        else:
            self._handshake(packets)
        if fault is not None:
            self._lost_framing(fault)
            return
        if self._refeed:
            self._refeed = False
            self.data_received(b"")

    def _to_session(self, session: Session, packets: list[Packet | Malformed]) -> None:
        """A read chunk's packets, in order, to the session (the loop every value takes).

        Consecutive ``Value`` frames (nearly all of them) go as one ``Bundle``, which the
        session treats part by part exactly as if each had come alone (docs/protocol.md
        6.16): its per-packet work (a clock reading, the dispatch) is paid once per run of
        values instead of once per frame, and ``packets_in`` still counts every frame.
        """
        handle, sink = session.handle, self._sink
        run: list[Value | Batch] = []
        for packet in packets:
            if type(packet) is Value:
                run.append(packet)
                continue
            if run:
                _values(session, run)
                run = []
            if isinstance(packet, Malformed):
                session.malformed_packet(packet.error, sink)
            else:
                handle(packet, "tcp")
        if run:
            _values(session, run)

    def _handshake(self, packets: list[Packet | Malformed]) -> None:
        """Packets before the session exists: a hello (and a proof); the rest, once the
        session is open, go to it."""
        for i, packet in enumerate(packets):
            if self._session is not None:
                self._to_session(self._session, packets[i:])
                return
            if isinstance(packet, Malformed):
                self._fatal(packet.error.code, packet.error.reason)
                return
            if isinstance(packet, Hello) and self._pending is None:
                self._hello(packet)
            elif isinstance(packet, AuthProof) and self._pending is not None:
                self._proof(packet)
            elif isinstance(packet, Disconnect) and self._pending is not None:
                self._gate.abandoned(packet, self._pending[0], self._peer)
                self._opened(self._pending[0], None)
                return
            else:
                wanted = "an AuthProof" if self._pending else "a Hello first"
                self._fatal(ErrorCode.UNEXPECTED,
                            f"expected {wanted}, got {type(packet).__name__}")
                return

    def _hello(self, hello: Hello) -> None:
        self._explained = True
        assert self._sink is not None
        assert self._transport is not None
        if self._transport.is_closing():  # refused (allow-list) or closing: no session
            return
        result = self._gate.hello(hello, self._peer)
        if isinstance(result, ServerHandshake):
            self._pending = (hello, result)
            self._sink.send(result.challenge)
        else:
            self._opened(hello, result)

    def _proof(self, proof: AuthProof) -> None:
        assert self._pending is not None
        hello, handshake = self._pending
        self._opened(hello, self._gate.finish(handshake, hello, proof, self._peer))

    def _opened(self, hello: Hello, result: Session | ConnectError | None) -> None:
        """Attach the session, or send the refusal (if any) and close."""
        assert self._sink is not None
        assert self._transport is not None
        if self._deadline is not None:
            self._deadline.cancel()
        self._registry.ctx.handshaking.discard(self._transport)
        if not isinstance(result, Session):
            if result is not None:
                self._sink.send(result)
            self._transport.close()
            return
        result.attach_tcp(self._sink, self._transport.close)
        if self._tls is not None and self._tls.identity is not None:
            result.identity = self._tls.identity  # a certificate outranks a key's name
        if self._guarded is not None and result.keys is not None:
            sealer, opener_key = stream_sealers(result.keys, server=True)
            self._guarded.protect_with(sealer.seal)
            assert isinstance(self._decoder, SealedStreamDecoder)
            self._decoder.install(RecordOpener(opener_key), strict=True)
            self._refeed = True
        self._session = result
        log.log(session_level(hello.name), "session %d (%s) opened over TCP from %s", result.id,
                hello.name, self._peer)
        secret = b""
        if self._tls is not None and type(result.codec) is PacketCodec:
            # No key handshake gave this session datagram keys: hand it a secret inside TLS.
            secret = os.urandom(KEY_SIZE)
            result.codec = sealed_codec(tls_datagram_keys(secret, result.token), server=True)
        self._sink.send(self._registry.ack(result, secret))
        result.acknowledged()

    def _lost_framing(self, fault: RemoteProtocolError) -> None:
        """A header (or record) that loses the framing, answered once every packet before it
        in the same read was handled: unless those packets ended the connection themselves
        (a Disconnect, a refused hello), whose later bytes are then never read, as they would
        not be had they come in a read of their own."""
        if self._transport is None or self._transport.is_closing():
            return
        self._registry.ctx.count("tcp_rejected_records" if fault.code == ErrorCode.AUTH_FAILED
                                 else "malformed")
        self._fatal(fault.code, fault.reason)

    def _fatal(self, code: ErrorCode, reason: str) -> None:
        """The byte stream cannot be trusted any more: say why, then close.

        Before a session exists the answer is a ConnectError ("no session"); inside a session
        it is an Error with the code, then a Disconnect, so the client's SDK reports the reason.
        """
        self._explained = True
        self._registry.ctx.notices.warn("malformed",
                                        f"closing TCP connection from {self._peer}: {reason}")
        if self._sink is None or self._transport is None:
            return
        if self._session is None:
            self._sink.send(ConnectError(int(code), reason))
        else:
            self._sink.send(Error(int(code), reason))
            self._session.close(reason, notify=True, code=int(code))
        self._transport.close()

    def _no_hello(self) -> None:
        if self._session is None and self._transport is not None:
            self._registry.ctx.count("handshake_timeouts")
            self._fatal(ErrorCode.UNEXPECTED, f"no complete hello within {HELLO_TIMEOUT:g} s")

    def _resume_reading(self) -> None:
        transport = self._transport
        if transport is not None and not transport.is_closing():
            transport.resume_reading()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
        if self._transport is not None:
            self._registry.ctx.handshaking.discard(self._transport)
        if self._tls is not None and not self._explained:
            self._tls.hung_up()
        if self._session is not None:
            self._session.close("TCP connection lost" if exc else "TCP connection closed",
                                notify=False)
            self._session = None
