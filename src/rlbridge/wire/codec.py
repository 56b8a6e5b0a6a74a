"""Bytes <-> packets for both transports; no sockets, no clocks.

Theory of operation. A TCP stream carries *frames*: an 8-byte header (magic ``RB``, protocol
version, flags, body length as big-endian u32) and a MessagePack body. A UDP datagram carries
exactly one packet: a 12-byte header (magic, version, flags, session token as big-endian u64)
and the body. The magic and version come first so that a stray client (an HTTP request, an old
SDK) is refused on its first bytes instead of being parsed as a length. Encoding writes the
header and the body into one buffer (``encode_into`` after a reserved header), no concatenation.

Errors are graded: a bad header loses the framing (``fatal=True``, close the connection), a
bad body inside a good frame costs only that packet (the session answers with an error packet
and goes on).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import msgspec

from rlbridge.wire.errors import ErrorCode, RemoteProtocolError
from rlbridge.wire.packets import PROTOCOL_VERSION, Packet

MAGIC = b"RB"
FRAME_HEADER = struct.Struct(">2sBBI")
DATAGRAM_HEADER = struct.Struct(">2sBBQ")
#: Largest frame body a decoder accepts unless told otherwise (bounded memory per session).
DEFAULT_MAX_PACKET = 1 << 20
#: A UDP datagram cannot be larger than this on IPv4.
MAX_DATAGRAM = 65507
FLAG_MAC = 0x01
#: First two bytes of a TLS handshake or alert record (TLS 1.0-1.3 all say 0x03 there).
_TLS_STARTS = (b"\x16\x03", b"\x15\x03")


@dataclass(frozen=True, slots=True)
class Malformed:
    """A frame that arrived whole but whose body is not a valid packet."""

    error: RemoteProtocolError


class PacketCodec:
    """Reusable msgspec encoder/decoder pair (creating them per packet costs more than a packet)."""

    def __init__(self) -> None:
        self._encoder = msgspec.msgpack.Encoder()
        self._decoder: msgspec.msgpack.Decoder[Packet] = msgspec.msgpack.Decoder(Packet)

    def encode_frame(self, packet: Packet) -> bytes:
        """One TCP frame: header + body."""
        buf = bytearray(FRAME_HEADER.size)
        self._encoder.encode_into(packet, buf, FRAME_HEADER.size)
        FRAME_HEADER.pack_into(buf, 0, MAGIC, PROTOCOL_VERSION, 0, len(buf) - FRAME_HEADER.size)
        return bytes(buf)

    def encode_frame_into(self, packet: Packet, buf: bytearray) -> None:
        """Append one TCP frame to ``buf`` (a send buffer holding several frames)."""
        start = len(buf)
        body = start + FRAME_HEADER.size
        self._encoder.encode_into(packet, buf, body)
        FRAME_HEADER.pack_into(buf, start, MAGIC, PROTOCOL_VERSION, 0, len(buf) - body)

    def encode_datagram(self, packet: Packet, token: int, flags: int = 0) -> bytes:
        """One UDP datagram: header with the session token + body."""
        buf = bytearray(DATAGRAM_HEADER.size)
        self._encoder.encode_into(packet, buf, DATAGRAM_HEADER.size)
        DATAGRAM_HEADER.pack_into(buf, 0, MAGIC, PROTOCOL_VERSION, flags, token)
        return bytes(buf)

    def decode_body(self, body: bytes | memoryview) -> Packet:
        """Decode one packet body; raise a non-fatal :class:`RemoteProtocolError` if invalid."""
        try:
            return self._decode(body)
        except RemoteProtocolError as exc:
            exc.tag, exc.channel = _salvage(body)
            raise

    def _decode(self, body: bytes | memoryview) -> Packet:
        try:
            return self._decoder.decode(body)
        except msgspec.ValidationError as exc:
            raise RemoteProtocolError(ErrorCode.MALFORMED, f"invalid packet: {exc}") from None
        except msgspec.DecodeError as exc:
            raise RemoteProtocolError(ErrorCode.MALFORMED, f"not a packet: {exc}") from None
        except UnicodeDecodeError as exc:  # msgspec raises it for a str that is not UTF-8
            raise RemoteProtocolError(
                ErrorCode.MALFORMED, f"not a packet: a string is not valid UTF-8 ({exc.reason})"
            ) from None
        except RecursionError:  # msgspec's guard against arrays nested without bound
            raise RemoteProtocolError(
                ErrorCode.MALFORMED, "not a packet: values nested too deeply"
            ) from None

    def decode_datagram(self, data: bytes) -> tuple[int, int, Packet]:
        """``(flags, token, packet)`` of one datagram; any error is about this datagram only."""
        if len(data) < DATAGRAM_HEADER.size:
            raise RemoteProtocolError(
                ErrorCode.MALFORMED,
                f"datagram of {len(data)} bytes is shorter than the {DATAGRAM_HEADER.size}-byte "
                "header",
            )
        magic, version, flags, token = DATAGRAM_HEADER.unpack_from(data)
        check_header(magic, version)
        try:
            return flags, token, self.decode_body(memoryview(data)[DATAGRAM_HEADER.size :])
        except RemoteProtocolError as exc:
            exc.token = token
            raise


def peek_header(data: bytes) -> tuple[int, int]:
    """``(flags, token)`` of a datagram without decoding it; ``(0, 0)`` for a bad header."""
    if len(data) < DATAGRAM_HEADER.size:
        return 0, 0
    magic, version, flags, token = DATAGRAM_HEADER.unpack_from(data)
    return (flags, token) if magic == MAGIC and version == PROTOCOL_VERSION else (0, 0)


def _salvage(body: bytes | memoryview) -> tuple[int | None, int | None]:
    """Tag and channel of an invalid body, if it is at least ``[int, int, ...]``."""
    try:
        raw = msgspec.msgpack.decode(body)
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError):
        return None, None
    if (isinstance(raw, list) and len(raw) >= 2 and type(raw[0]) is int
            and type(raw[1]) is int and 0 <= raw[1] <= 0xFFFF_FFFF):
        return raw[0], raw[1]
    return None, None


def check_header(magic: bytes, version: int) -> None:
    """Refuse a header that is not ours, or ours in a version this code does not speak."""
    if magic in _TLS_STARTS:
        raise RemoteProtocolError(
            ErrorCode.MALFORMED,
            "a TLS handshake on a port without TLS: connect without TLS, or start the server "
            "with --tls-cert and --tls-key",
            fatal=True,
        )
    if magic != MAGIC:
        raise RemoteProtocolError(
            ErrorCode.MALFORMED,
            f"bad magic {magic!r}: this port speaks the rlbridge protocol (magic b'RB')",
            fatal=True,
        )
    if version != PROTOCOL_VERSION:
        raise RemoteProtocolError(
            ErrorCode.UNSUPPORTED_VERSION,
            f"protocol version {version} is not supported; this peer speaks version "
            f"{PROTOCOL_VERSION}",
            fatal=True,
        )


class FrameDecoder:
    """Turns a TCP byte stream, in chunks of any size, into packets.

    ``feed`` returns every packet completed by the new bytes (several when frames arrive
    coalesced, none when a frame is still partial). A frame larger than ``max_packet`` is refused
    from its header, before its body is buffered, so a peer cannot make us allocate without bound.
    """

    def __init__(self, codec: PacketCodec | None = None, max_packet: int = DEFAULT_MAX_PACKET):
        self._codec = codec or PacketCodec()
        self._buf = bytearray()
        self._max = max_packet
        self._broken: RemoteProtocolError | None = None

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the rest of a frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Packet | Malformed]:
        if self._broken is not None:
            raise self._broken
        buf = self._buf
        buf += data
        out: list[Packet | Malformed] = []
        pos = 0
        size = len(buf)
        hsize = FRAME_HEADER.size
        view = memoryview(buf)
        try:
            while size - pos >= hsize:
                magic, version, _flags, length = FRAME_HEADER.unpack_from(buf, pos)
                if magic != MAGIC or version != PROTOCOL_VERSION:
                    try:
                        check_header(magic, version)
                    except RemoteProtocolError as exc:
                        self._broken = exc
                        raise
                if length > self._max:
                    self._broken = RemoteProtocolError(
                        ErrorCode.TOO_LARGE,
                        f"frame of {length} bytes exceeds the limit of {self._max} bytes",
                        fatal=True,
                    )
                    raise self._broken
                end = pos + hsize + length
                if end > size:
                    break
                try:
                    out.append(self._codec.decode_body(view[pos + hsize : end]))
                except RemoteProtocolError as exc:
                    # A fresh error: the caught one's traceback and context hold a view of
                    # ``buf``, which would make the ``del buf[:pos]`` below (and every later
                    # ``feed``) fail with BufferError.
                    fresh = RemoteProtocolError(exc.code, exc.reason)
                    fresh.tag, fresh.channel = exc.tag, exc.channel
                    out.append(Malformed(fresh))
                pos = end
        finally:
            view.release()
        if pos:
            del buf[:pos]
        return out
