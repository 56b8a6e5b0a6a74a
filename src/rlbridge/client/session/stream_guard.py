"""What protects one session's TCP byte stream on the client: TLS, sealed records, or nothing.

:class:`~rlbridge.client.session.connection.Connection` hands every write through
:meth:`StreamGuard.
protect` (under its TCP write lock, so TLS records and sealed records leave in the order their
counters say) and every read through :meth:`StreamGuard.open`. The TLS engine is one OpenSSL
object used by the receive thread and the writing threads alike, which OpenSSL does not allow
concurrently: ``tls_lock`` serialises it, held only while bytes are transformed, never across
a blocking ``send`` or ``recv`` (rlbridge/tls/engine.py says more).
"""

from __future__ import annotations

import ssl
import threading

from rlbridge.tls import TlsEngine
from rlbridge.wire import ErrorCode, FrameDecoder, RemoteProtocolError
from rlbridge.wire.records import RecordSealer, SealedStreamDecoder


class StreamGuard:
    """The current session's stream protection; :meth:`reset` at every new handshake."""

    def __init__(self) -> None:
        self.tls_lock = threading.Lock()
        self.tls: TlsEngine | None = None
        #: A pre-shared-key session without TLS: its writes become sealed records.
        self.sealer: RecordSealer | None = None
        #: The handshake's frame decoder, which the receive thread goes on with.
        self.decoder: FrameDecoder | SealedStreamDecoder | None = None

    def reset(self) -> None:
        self.tls = self.sealer = self.decoder = None

    def protect(self, data: bytes | bytearray) -> bytes | bytearray:
        """What to write for ``data`` (call under the connection's TCP write lock)."""
        engine = self.tls
        if engine is not None:
            with self.tls_lock:
                return engine.send(data)
        if self.sealer is not None and data:
            return self.sealer.seal(data)
        return data

    def open(self, data: bytes) -> tuple[bytes, bool]:
        """The plaintext of bytes read, all of it, and whether TLS has bytes to send now.

        Raises :class:`~rlbridge.wire.RemoteProtocolError` when TLS refuses them.
        """
        engine = self.tls
        if engine is None:
            return data, False
        try:
            with self.tls_lock:
                return engine.receive(data), engine.wants_write
        except ssl.SSLError as exc:
            raise RemoteProtocolError(ErrorCode.AUTH_FAILED, f"TLS: {exc.reason or exc}",
                                      fatal=True) from None
