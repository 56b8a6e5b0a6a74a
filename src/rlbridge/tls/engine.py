"""TLS over memory buffers (``ssl.SSLObject`` + ``MemoryBIO``): bytes in, bytes out.

Why not ``ssl.SSLSocket``. The client reads its TCP socket in one thread (waiting in
``select``) and writes it from others (send thread, heartbeats, requests). An ``SSLSocket``
decrypts whole records and keeps what the caller did not read yet in its own buffer
(``pending()``), where ``select`` cannot see it: values would wait for the next record. And
OpenSSL does not allow ``SSL_read`` and ``SSL_write`` on one connection from two threads at
once, which is exactly that thread layout. Here the socket stays a plain socket; this object
only transforms bytes, the caller serialises calls to it with one lock held for microseconds
(never across a blocking ``send``/``recv``), and :meth:`receive` always returns *all* the
plaintext the bytes fed so far complete, so nothing is left where ``select`` cannot see it.
The server drives the same class from its asyncio protocol (one thread, no lock needed).
"""

from __future__ import annotations

import ssl
from typing import Any

#: Plaintext taken from the TLS object per ``read`` call (a record holds at most 16 KiB).
_READ = 1 << 18


class TlsEngine:
    """One end of a TLS connection; feed it what the socket read, send what it returns."""

    def __init__(self, context: ssl.SSLContext, *, server_side: bool,
                 server_hostname: str | None = None) -> None:
        self._in = ssl.MemoryBIO()
        self._out = ssl.MemoryBIO()
        self._tls = context.wrap_bio(self._in, self._out, server_side=server_side,
                                     server_hostname=server_hostname)
        self.handshake_done = False
        #: The peer ended TLS in order (close_notify): no more plaintext will come.
        self.closed = False

    def start(self) -> bytes:
        """The first bytes to send (the client's hello; nothing for a server)."""
        self._step_handshake()
        return self._out.read()

    def receive(self, data: bytes) -> bytes:
        """Feed bytes read from the socket; return every plaintext byte they complete.

        Drives the handshake while it runs. Raises ``ssl.SSLError`` when the peer is not
        speaking TLS, is refused (certificate), or sent something forged; the bytes to send
        (an alert, a handshake flight) are then in :meth:`outgoing`.
        """
        if data:
            self._in.write(data)
        if not self.handshake_done and not self._step_handshake():
            return b""
        chunks: list[bytes] = []
        while True:
            try:
                chunk = self._tls.read(_READ)
            except ssl.SSLWantReadError:
                break
            except ssl.SSLZeroReturnError:
                self.closed = True
                break
            if not chunk:
                break
            chunks.append(chunk)
        return b"".join(chunks)

    def send(self, plaintext: bytes | bytearray | memoryview) -> bytes:
        """Encrypt ``plaintext``; return the bytes to write (with anything else due out)."""
        if plaintext:
            self._tls.write(plaintext)  # a memory BIO takes everything: no partial write
        return self._out.read()

    def outgoing(self) -> bytes:
        """Bytes due out that no :meth:`send` carried (handshake flights, alerts, tickets)."""
        return self._out.read()

    @property
    def wants_write(self) -> bool:
        return self._out.pending > 0

    def peer_certificate(self) -> bytes | None:
        """The peer's certificate (DER), once the handshake is done; None if it sent none."""
        return self._tls.getpeercert(binary_form=True)

    def peer_common_name(self) -> str | None:
        """The common name of the peer's *verified* certificate (mutual TLS), else None."""
        cert = self._tls.getpeercert()
        if not cert:
            return None
        subject: Any = cert.get("subject", ())
        for rdn in subject:
            for key, value in rdn:
                if key == "commonName":
                    return str(value)
        return None

    def version(self) -> str | None:
        return self._tls.version()

    def _step_handshake(self) -> bool:
        try:
            self._tls.do_handshake()
        except ssl.SSLWantReadError:
            return False
        self.handshake_done = True
        return True
