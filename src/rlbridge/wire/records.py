"""Sealed TCP records, sans-IO: the frame stream of a pre-shared-key session without TLS.

After the handshake such a session sends its frames as records,
``frame header(8, flag SEALED, length) | ciphertext | tag(16)``, sealed with ChaCha20-Poly1305
under the stream key of its direction (:mod:`rlbridge.wire.seal`), with an implicit counter
(0, 1, 2, ... as in TLS; TCP keeps order) as nonce and the 8-byte header as associated data.
A record injected, dropped, repeated or reordered by anyone without the key does not open,
and the connection ends with that reason. A record carries up to ``RECORD_MAX`` bytes of the
frame stream; a frame may span records.

:class:`SealedStreamDecoder` reads a stream that starts in plain frames (the handshake) and
turns into records once :meth:`~SealedStreamDecoder.install` gave it the key: a record that
arrives before the key waits in the buffer (the proof that yields the key may sit in the same
read), and once strict, a plain frame is refused as injected.
"""

from __future__ import annotations

from rlbridge.errors import ErrorCode, RemoteProtocolError
from rlbridge.wire.aead import (
    BULK_FROM,
    InvalidTag,
    bulk_chacha20_poly1305,
    chacha20_poly1305,
)
from rlbridge.wire.codec import (
    DEFAULT_MAX_PACKET,
    FRAME_HEADER,
    MAGIC,
    FrameDecoder,
    Malformed,
    PacketCodec,
    check_header,
)
from rlbridge.wire.packets import PROTOCOL_VERSION, Packet
from rlbridge.wire.seal import FLAG_SEALED, TAG_SIZE, SessionKeys, nonce

#: Largest plaintext of one TCP record (a frame larger than this spans records).
RECORD_MAX = 1 << 16


class RecordSealer:
    """Frames -> sealed TCP records, for one direction (implicit counter: call in send order)."""

    def __init__(self, key: bytes) -> None:
        self._seal = chacha20_poly1305(key).seal_counted
        self._seal_bulk = bulk_chacha20_poly1305(key).seal_counted
        self._counter = 0

    def seal(self, frames: bytes | bytearray | memoryview) -> bytes:
        view = memoryview(frames)
        out = bytearray()
        for start in range(0, len(view), RECORD_MAX):
            chunk = view[start:start + RECORD_MAX]
            head = FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, FLAG_SEALED,
                                     len(chunk) + TAG_SIZE)
            seal = self._seal if len(chunk) < BULK_FROM else self._seal_bulk
            out += seal(self._counter, head, chunk)
            self._counter += 1
        return bytes(out)


def stream_sealers(keys: SessionKeys, *, server: bool) -> tuple[RecordSealer, bytes]:
    """This side's record sealer, and the key its peer's records open with."""
    if server:
        return RecordSealer(keys.stream_server_to_client), keys.stream_client_to_server
    return RecordSealer(keys.stream_client_to_server), keys.stream_server_to_client


class RecordOpener:
    """Sealed records -> the frame stream inside them, for one direction."""

    def __init__(self, key: bytes) -> None:
        self._open = chacha20_poly1305(key).decrypt
        self._open_bulk = bulk_chacha20_poly1305(key).decrypt
        self._counter = 0

    def open(self, head: bytes | memoryview, sealed: bytes | memoryview) -> bytes:
        opener = self._open if len(sealed) < BULK_FROM + TAG_SIZE else self._open_bulk
        try:
            plain = opener(nonce(self._counter), sealed, head)
        except InvalidTag:
            raise RemoteProtocolError(
                ErrorCode.AUTH_FAILED,
                f"TCP record {self._counter} does not open under this session's key: "
                "injected, altered, replayed or reordered on the way; the session ends",
                fatal=True) from None
        self._counter += 1
        return plain


class SealedStreamDecoder:
    """Plain frames, then sealed records, into packets (module docstring)."""

    def __init__(self, codec: PacketCodec | None = None,
                 max_packet: int = DEFAULT_MAX_PACKET,
                 stop_after: type[Packet] | None = None) -> None:
        self._frames = FrameDecoder(codec, max_packet)
        self._max = max_packet
        #: The plain packet after which the key comes (the server's AuthProof): decoding stops
        #: there, so nothing sent after it in the same read is taken as plain; it is read
        #: again once the key is installed (strict), as records or refused.
        self._stop_after = stop_after
        self._buf = bytearray()
        self._opener: RecordOpener | None = None
        self._strict = False
        self._broken: RemoteProtocolError | None = None
        #: Records opened so far.
        self.records = 0

    @property
    def buffered(self) -> int:
        return len(self._buf) + self._frames.buffered

    @property
    def installed(self) -> bool:
        """True once records can be opened (the key exists)."""
        return self._opener is not None

    def install(self, opener: RecordOpener, *, strict: bool) -> None:
        """Open records from now on. ``strict``: refuse plain frames at once (the server,
        which installs the key on the proof); else from the first record on (the client,
        which may still get a plain ConnectError from a server that refused its proof)."""
        self._opener = opener
        self._strict = strict

    def feed(self, data: bytes) -> list[Packet | Malformed]:
        if self._broken is not None:
            raise self._broken
        try:
            return self._feed(data)
        except RemoteProtocolError as exc:
            if exc.fatal:
                self._broken = exc
            raise

    def _feed(self, data: bytes) -> list[Packet | Malformed]:
        buf = self._buf
        buf += data
        out: list[Packet | Malformed] = []
        pos, size, hsize = 0, len(buf), FRAME_HEADER.size
        try:
            while size - pos >= hsize:
                magic, version, flags, length = FRAME_HEADER.unpack_from(buf, pos)
                check_header(magic, version)
                end = pos + hsize + length
                if flags & FLAG_SEALED:
                    if self._opener is None:  # the key is not there yet: wait in the buffer
                        if size - pos > RECORD_MAX + TAG_SIZE + hsize:
                            raise RemoteProtocolError(
                                ErrorCode.UNEXPECTED, "sealed records before the handshake "
                                "gave their key", fatal=True)
                        break
                    if length > RECORD_MAX + TAG_SIZE:
                        raise RemoteProtocolError(
                            ErrorCode.TOO_LARGE, f"TCP record of {length} bytes exceeds "
                            f"the limit of {RECORD_MAX + TAG_SIZE}", fatal=True)
                    if end > size:
                        break
                    plain = self._opener.open(bytes(buf[pos:pos + hsize]),
                                              bytes(buf[pos + hsize:end]))
                    self.records += 1
                    out += self._frames.feed(plain)
                else:
                    if self._strict or self.records:
                        raise RemoteProtocolError(
                            ErrorCode.AUTH_FAILED, "unsealed frame on a sealed TCP "
                            "session (injected on the way?); the session ends", fatal=True)
                    if length > self._max:
                        raise RemoteProtocolError(
                            ErrorCode.TOO_LARGE, f"frame of {length} bytes exceeds the limit "
                            f"of {self._max} bytes", fatal=True)
                    if end > size:
                        break
                    got = self._frames.feed(bytes(buf[pos:end]))
                    out += got
                    if (self._stop_after is not None and self._opener is None
                            and any(isinstance(p, self._stop_after) for p in got)):
                        pos = end
                        break
                pos = end
        finally:
            if pos:
                del buf[:pos]
        return out
