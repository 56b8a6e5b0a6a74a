"""The UDP endpoint: datagrams to sessions by token, never by source address alone."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from typing import cast

from rlbridge.server.registry import SessionRegistry
from rlbridge.server.sinks import UdpSink
from rlbridge.wire import ConnectError, Hello, RemoteProtocolError

log = logging.getLogger("rlbridge.server")

#: Bytes of queued datagrams the server asks the kernel for (see ``connection_made``).
RECEIVE_BUFFER = 4 << 20


class UdpEndpoint(asyncio.DatagramProtocol):
    """One socket for every UDP client.

    A datagram with token 0 may only be a hello: it creates a UDP-only session (thesis 4.1.1)
    and the reply carries the token. Any other datagram must carry a live token; its source
    address becomes the session's UDP address (also how a TCP session starts using UDP
    channels). Datagrams with unknown tokens are dropped and counted, never answered, so the
    endpoint cannot be used to reflect traffic at a third party.
    """

    def __init__(self, registry: SessionRegistry) -> None:
        self._registry = registry
        self._transport: asyncio.DatagramTransport | None = None
        # A retransmitted hello (its ack was lost) gets the same session, not a second one.
        self._hello_sessions: dict[tuple[tuple[str, int], str], int] = {}
        registry.on_forget.append(lambda s: self.forget(s.id))

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = cast(asyncio.DatagramTransport, transport)
        self._registry.ctx.udp_transport = self._transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            # Every client's datagrams queue here while the loop is busy; the default buffer
            # (~200 KiB, under 100 full datagrams) drops a single client's burst. The kernel
            # caps the request at net.core.rmem_max; drops that remain show as sequence gaps.
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        ctx = self._registry.ctx
        try:
            _flags, token, packet = ctx.codec.decode_datagram(data)
        except RemoteProtocolError as exc:
            ctx.count("udp_malformed")
            log.debug("dropped datagram from %s: %s", addr, exc.reason)
            # A live token proves the sender is the client: tell it what was wrong.
            known = self._registry.by_token(exc.token) if exc.token else None
            if known is not None and known.udp is not None:
                known.malformed_packet(exc, known.udp)
            return
        if token == 0:
            if isinstance(packet, Hello):
                self._hello(packet, addr)
            else:
                ctx.count("udp_no_token")
            return
        session = self._registry.by_token(token)
        if session is None:
            ctx.count("udp_bad_token")
            return
        session.bytes_in += len(data)
        session.attach_udp(addr)
        session.handle(packet, "udp")

    def _hello(self, hello: Hello, addr: tuple[str, int]) -> None:
        assert self._transport is not None
        ctx = self._registry.ctx
        key = (addr, hello.name)
        known = self._hello_sessions.get(key)
        session = None
        if known is not None:
            session = next((s for s in self._registry if s.id == known and not s.closed), None)
        if session is None:
            result = self._registry.open(hello)
            if isinstance(result, ConnectError):
                self._transport.sendto(ctx.codec.encode_datagram(result, 0), addr)
                return
            session = result
            self._hello_sessions[key] = session.id
            log.info("session %d (%s) opened over UDP from %s", session.id, hello.name, addr)
        session.attach_udp(addr)
        sink = session.udp
        assert isinstance(sink, UdpSink)
        sink.send(self._registry.ack(session))

    def forget(self, session_id: int) -> None:
        for key, sid in list(self._hello_sessions.items()):
            if sid == session_id:
                del self._hello_sessions[key]
