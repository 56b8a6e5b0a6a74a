"""The server's end of a TLS connection: handshake, refusals said once, plaintext out.

Driven by :class:`~rlbridge.server.tcp.TcpConnection` with the bytes the socket delivered, it
returns the plaintext for the frame decoder and writes handshake flights and alerts itself.
A client that does not speak TLS (its first bytes are the rlbridge magic) is answered in
plain protocol, a ``ConnectError`` saying this server needs TLS, so the client's user reads
why instead of a dropped connection; a handshake that fails (no client certificate, a CA the
client refuses) is logged with OpenSSL's reason (at most once per interval: the server's
notices) and counted (``tls_failed``), and so is a client that hangs up after the handshake
without a hello (a client refusing this server's certificate by its pinned fingerprint checks
it then, and says nothing to the server). Either way only this connection closes.
"""

from __future__ import annotations

import asyncio
import ssl

from rlbridge.server.context import ServerContext
from rlbridge.server.guarded import GuardedTransport
from rlbridge.tls import TlsEngine
from rlbridge.wire import MAGIC, ConnectError, ErrorCode

#: The notice kind of a failed handshake: its own, so a plaintext client's refusal just before
#: does not hold it back for the interval (each kind is logged once per interval).
HANDSHAKE = "TLS handshake"


class ServerTls:
    """TLS for one accepted connection; :attr:`transport` is what the sinks write to."""

    def __init__(self, context: ssl.SSLContext, raw: asyncio.Transport, ctx: ServerContext,
                 peer: str) -> None:
        self._engine = TlsEngine(context, server_side=True)
        self._raw = raw
        self._ctx = ctx
        self._peer = peer
        self._first = True
        self._refused = False
        self.transport = GuardedTransport(raw, self._engine.send)
        #: The verified client certificate's common name (mutual TLS), once known.
        self.identity: str | None = None

    def received(self, data: bytes) -> bytes | None:
        """Plaintext completed by ``data``; None when the connection was refused and closed."""
        first, self._first = self._first, False
        if first and data.startswith(MAGIC):
            self._ctx.count("tls_plaintext_clients")
            self._ctx.notices.warn("plaintext client", f"refused a plaintext client from "
                                   f"{self._peer}: "
                                   "this server requires TLS")
            self._refused = True
            self._raw.write(self._ctx.codec.encode_frame(ConnectError(
                int(ErrorCode.AUTH_FAILED), "this server requires TLS: connect with TLS "
                "(and the server's CA file or certificate fingerprint)")))
            self._raw.close()
            return None
        engine = self._engine
        was_done = engine.handshake_done
        try:
            plain = engine.receive(data)
        except ssl.SSLError as exc:
            self._refused = True
            self._ctx.count("tls_failed")
            self._ctx.notices.warn(HANDSHAKE, f"TLS with {self._peer} failed: "
                                   f"{exc.reason or exc}")
            alert = engine.outgoing()
            if alert:
                self._raw.write(alert)
            self._raw.close()
            return None
        out = engine.outgoing()
        if out:
            self._raw.write(out)
        if engine.handshake_done and not was_done:
            self.identity = engine.peer_common_name()
            self._ctx.count("tls_sessions")
        if engine.closed:
            self._raw.close()
        return plain

    def hung_up(self) -> None:
        """The connection closed before any hello: count and say so, unless it was refused
        here already or never sent a byte (a port probe)."""
        if self._refused or self._first:
            return
        self._ctx.count("tls_failed")
        when = ("after the TLS handshake, before its hello: it may not accept this server's "
                "certificate (a --fingerprint pinned to another, or another --ca)"
                if self._engine.handshake_done else "during the TLS handshake")
        self._ctx.notices.warn(HANDSHAKE, f"TLS client {self._peer} hung up {when}")
