"""The client's TLS handshake over its plain TCP socket, and what its failures say.

The socket stays a plain socket (:mod:`rlbridge.tls.engine` says why); this drives the engine
through the handshake with the connection's deadline, and :meth:`Connection.close` can abort it
through the wake-up socket like any other handshake step. Each failure is one sentence that
says which side is wrong: a certificate that does not verify (and how to trust it), a server
that does not speak TLS, a pinned fingerprint that does not match.
"""

from __future__ import annotations

import contextlib
import select
import socket
import ssl
import time
from typing import TYPE_CHECKING

from rlbridge.errors import ConnectionClosed, ConnectionFailed, TlsError, TlsFailed
from rlbridge.tls import TlsEngine
from rlbridge.wire import MAGIC

if TYPE_CHECKING:
    from rlbridge.csp.session_owner import SessionOwner

#: First bytes of a TLS record (handshake or alert, TLS 1.x): what a TLS server answers with.
TLS_RECORD_STARTS = (b"\x16\x03", b"\x15\x03")


def start_tls(conn: SessionOwner, sock: socket.socket, wake: socket.socket) -> TlsEngine:
    """Run the TLS handshake on connected ``sock``; return the engine for the session."""
    settings = conn.tls
    assert settings is not None
    where = f"{conn.host}:{conn.port}"
    engine = TlsEngine(settings.context, server_side=False, server_hostname=conn.host)
    deadline = time.monotonic() + conn.timeout
    try:
        out = engine.start()
        while True:
            if out:
                sock.sendall(out)
            if engine.handshake_done:
                break
            ready, _, _ = select.select([sock, wake], [], [],
                                        max(0.0, deadline - time.monotonic()))
            if wake in ready:
                raise ConnectionClosed("connection closed while connecting")
            if not ready:
                raise ConnectionFailed(f"no TLS answer from {where} within {conn.timeout} s")
            data = sock.recv(65536)
            if not data:
                raise TlsFailed(f"{where} closed the connection during the TLS handshake")
            if data.startswith(MAGIC):
                raise TlsFailed(f"{where} does not use TLS (it answered in plain rlbridge "
                                "protocol): connect without TLS, or start the server with "
                                "--tls-cert and --tls-key")
            engine.receive(data)
            out = engine.outgoing()
    except ssl.SSLError as exc:
        with contextlib.suppress(OSError):  # the alert: the server logs why we left
            sock.sendall(engine.outgoing())
        raise _failed(exc, where) from None
    try:
        settings.check(engine.peer_certificate())
    except TlsError as exc:
        raise TlsFailed(f"TLS: {where}: {exc}") from None
    return engine


def _failed(exc: ssl.SSLError, where: str) -> TlsFailed:
    if isinstance(exc, ssl.SSLCertVerificationError):
        return TlsFailed(f"TLS: the certificate of {where} does not verify: "
                        f"{exc.verify_message}; trust it with its CA file, or pin its "
                        "fingerprint (`rlbridge tls init` prints it)")
    return TlsFailed(f"TLS handshake with {where} failed: {exc.reason or exc}")


def plaintext_refused(data: bytes, where: str) -> TlsFailed | None:
    """A plaintext client's first answer that is a TLS record: the server wants TLS."""
    if data[:2] in TLS_RECORD_STARTS:
        return TlsFailed(f"{where} requires TLS: connect with TLS (and the server's CA file "
                         "or certificate fingerprint)")
    return None
