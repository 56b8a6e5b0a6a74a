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
read), and once strict, anything but a record is refused as injected (:func:`refuse_record`).
On the server, which knows the packet after which the key comes (``stop_after``), a record
before it is refused at once: nothing sealed can precede the key.
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
        """As :meth:`FrameDecoder.feed <rlbridge.wire.codec.FrameDecoder.feed>`: raises the
        fault, dropping the packets before it (a receiver that must act on those first calls
        :meth:`feed_until_fault`)."""
        packets, fault = self.feed_until_fault(data)
        if fault is not None:
            raise fault
        return packets

    def feed_until_fault(
        self, data: bytes
    ) -> tuple[list[Packet | Malformed], RemoteProtocolError | None]:
        """The packets the bytes so far complete, and the fault that ended the stream, if one
        did: every packet of the records (or plain frames) before it comes out with it,
        those of the record whose inner frame broke included (as ``FrameDecoder``'s
        :meth:`~rlbridge.wire.codec.FrameDecoder.feed_until_fault`)."""
        if self._broken is not None:
            return [], self._broken
        out: list[Packet | Malformed] = []
        try:
            self._feed(data, out)
        except RemoteProtocolError as exc:  # every error _feed raises loses the stream
            self._broken = exc
            self._buf.clear()
            return out, exc
        return out, None

    def _frames_of(self, chunk: bytes, out: list[Packet | Malformed]) -> list[Packet | Malformed]:
        """The packets of a stretch of the frame stream onto ``out`` (and returned); a
        fault inside it is raised once those before it are on ``out``."""
        got, fault = self._frames.feed_until_fault(chunk)
        out += got
        if fault is not None:
            raise fault
        return got

    def _feed(self, data: bytes, out: list[Packet | Malformed]) -> None:
        """Decode onto ``out``, so that what was decoded before an error raised stays there."""
        buf = self._buf
        buf += data
        pos, size, hsize = 0, len(buf), FRAME_HEADER.size
        try:
            while size - pos >= hsize:
                magic, version, flags, length = FRAME_HEADER.unpack_from(buf, pos)
                end = pos + hsize + length
                if not (self._strict or self.records):  # plain frames may still come
                    check_header(magic, version)
                    if not flags & FLAG_SEALED:
                        if length > self._max:
                            raise RemoteProtocolError(
                                ErrorCode.TOO_LARGE, f"frame of {length} bytes exceeds the "
                                f"limit of {self._max} bytes", fatal=True)
                        if end > size:
                            break
                        got = self._frames_of(bytes(buf[pos:end]), out)
                        pos = end
                        if (self._stop_after is not None and self._opener is None
                                and any(isinstance(p, self._stop_after) for p in got)):
                            break
                        continue
                    if self._opener is None:
                        if self._stop_after is not None:  # nothing sealed precedes the key
                            raise RemoteProtocolError(
                                ErrorCode.MALFORMED, "a sealed record before the key "
                                "handshake gave its key", fatal=True)
                        if size - pos > RECORD_MAX + TAG_SIZE + hsize:  # waits for the key
                            raise RemoteProtocolError(
                                ErrorCode.UNEXPECTED, "sealed records before the handshake "
                                "gave their key", fatal=True)
                        break
                refuse_record(magic, version, flags, length)
                if end > size:
                    break
                assert self._opener is not None  # strict or records: installed
                plain = self._opener.open(bytes(buf[pos:pos + hsize]),
                                          bytes(buf[pos + hsize:end]))
                self.records += 1
                pos = end
                self._frames_of(plain, out)
        finally:
            if pos:
                del buf[:pos]


def refuse_record(magic: bytes, version: int, flags: int, length: int) -> None:
    """Once a stream is sealed every header is a record's: anything else (a plain frame, a
    header that is not ours, a record longer than the limit) is refused as injected, before
    its body is read (docs/protocol.md 16.5). The limit bounds what a receiver buffers: the
    length is authenticated only with the record, so it cannot be trusted before."""
    if magic != MAGIC or version != PROTOCOL_VERSION:
        raise RemoteProtocolError(
            ErrorCode.AUTH_FAILED, f"not a sealed record (header {magic!r} version {version}) "
            "on a sealed TCP session (injected on the way?); the session ends", fatal=True)
    if not flags & FLAG_SEALED:
        raise RemoteProtocolError(
            ErrorCode.AUTH_FAILED, "unsealed frame on a sealed TCP session (injected on the "
            "way?); the session ends", fatal=True)
    if length > RECORD_MAX + TAG_SIZE:
        raise RemoteProtocolError(
            ErrorCode.AUTH_FAILED, f"TCP record of {length} bytes (length field) exceeds the "
            f"limit of {RECORD_MAX + TAG_SIZE} (injected on the way?); the session ends",
            fatal=True)
