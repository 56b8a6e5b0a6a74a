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
from typing import Any

import msgspec
from mypy_extensions import mypyc_attr

from rlbridge.errors import ErrorCode, RemoteProtocolError
from rlbridge.wire.packets import PROTOCOL_VERSION, Batch, Bundle, Packet, Value

MAGIC = b"RB"
FRAME_HEADER = struct.Struct(">2sBBI")
DATAGRAM_HEADER = struct.Struct(">2sBBQ")
_FRAME_HEAD: int = FRAME_HEADER.size
#: Largest frame body a decoder accepts unless told otherwise (bounded memory per session).
DEFAULT_MAX_PACKET = 1 << 20
#: A UDP datagram cannot be larger than this on IPv4.
MAX_DATAGRAM = 65507
FLAG_MAC = 0x01
#: Set on every datagram of a peer that reads ``Bundle`` packets (docs/protocol.md 6.16): the
#: other side bundles only to a peer that has said so, so an older client never meets one.
FLAG_BUNDLES = 0x80
#: First two bytes of a TLS handshake or alert record (TLS 1.0-1.3 all say 0x03 there).
_TLS_STARTS = (b"\x16\x03", b"\x15\x03")


@dataclass(frozen=True, slots=True)
class Malformed:
    """A frame that arrived whole but whose body is not a valid packet."""

    error: RemoteProtocolError


class PartlyMalformed(RemoteProtocolError):
    """A bundle some of whose parts are invalid: ``bundle`` holds the valid parts.

    Raised (non-fatal) instead of losing the whole bundle; ``errors`` has one error per invalid
    part, with that part's tag and channel salvaged, so each is answered as it would be alone.
    A receiver that does not look inside treats it as any malformed packet.
    """

    def __init__(self, bundle: Bundle, errors: list[RemoteProtocolError]) -> None:
        super().__init__(ErrorCode.MALFORMED, f"{len(errors)} of "
                         f"{len(errors) + len(bundle.parts)} bundle parts are invalid: "
                         + "; ".join(e.reason for e in errors))
        self.tag = BUNDLE_TAG
        self.bundle = bundle
        self.errors = errors


BUNDLE_TAG: int = Bundle.__struct_config__.tag  # type: ignore[assignment]


# Compiled by mypyc (rlbridge/_compiled.py); SealedCodec (wire/seal.py) subclasses it.
@mypyc_attr(allow_interpreted_subclasses=True)
class PacketCodec:
    """Reusable msgspec encoder/decoder pair (creating them per packet costs more than a packet)."""

    def __init__(self) -> None:
        self._encoder = msgspec.msgpack.Encoder()
        self._decoder: msgspec.msgpack.Decoder[Packet] = msgspec.msgpack.Decoder(Packet)
        self._part_decoder: msgspec.msgpack.Decoder[Value | Batch] = msgspec.msgpack.Decoder(
            Value | Batch)
        #: One body to a packet, msgspec's own errors unchanged: for loops that decode many
        #: bodies and grade the rare bad one with :meth:`decode_body` (``FrameDecoder``).
        self.raw_decode = self._decoder.decode

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
            raw = _raw(body)
            exc.tag, exc.channel = _tag_and_channel(raw)
            if isinstance(raw, list) and raw and raw[0] == BUNDLE_TAG and type(raw[0]) is int:
                exc.tag = BUNDLE_TAG
                self._salvage_bundle(raw)
            raise

    def _salvage_bundle(self, raw: list[Any]) -> None:
        """Raise the valid parts of an invalid bundle, each invalid part's error beside them.

        Raised here, never held in a local of ``decode_body``: the exception would then sit in
        its own traceback's frame, a cycle that keeps the body's memoryview (and the TCP
        decoder's buffer) alive until the garbage collector runs.
        """
        if len(raw) < 2 or not isinstance(raw[1], list):
            return
        good: list[Value | Batch] = []
        errors: list[RemoteProtocolError] = []
        for i, part in enumerate(raw[1]):
            try:
                good.append(self._part_decoder.decode(msgspec.msgpack.encode(part)))
            except (msgspec.ValidationError, msgspec.DecodeError, RecursionError) as exc:
                error = RemoteProtocolError(ErrorCode.MALFORMED,
                                            f"bundle part {i}: invalid packet: {exc}")
                error.tag, error.channel = _tag_and_channel(part)
                errors.append(error)
        raise PartlyMalformed(Bundle(good), errors) from None

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


def _raw(body: bytes | memoryview) -> object:
    """An invalid body decoded without a schema (``None`` if it is not even MessagePack)."""
    try:
        return msgspec.msgpack.decode(body)
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError):
        return None


def _tag_and_channel(raw: object) -> tuple[int | None, int | None]:
    """Tag and channel of an invalid body, if it is at least ``[int, int, ...]``."""
    if (isinstance(raw, list) and len(raw) >= 2 and type(raw[0]) is int
            and type(raw[1]) is int and 0 <= raw[1] <= 0xFFFF_FFFF):
        return raw[0], raw[1]
    return None, None


def header_error(magic: bytes, version: int) -> RemoteProtocolError | None:
    """Why a header is not ours, or ours in a version this code does not speak (``None``: it
    is ours). Returned, not raised: a decoder stops on it and still hands out what came
    before (:meth:`FrameDecoder.feed_until_fault`)."""
    if magic in _TLS_STARTS:
        return RemoteProtocolError(
            ErrorCode.MALFORMED,
            "a TLS handshake on a port without TLS: connect without TLS, or start the server "
            "with --tls-cert and --tls-key",
            fatal=True,
        )
    if magic != MAGIC:
        return RemoteProtocolError(
            ErrorCode.MALFORMED,
            f"bad magic {magic!r}: this port speaks the rlbridge protocol (magic b'RB')",
            fatal=True,
        )
    if version != PROTOCOL_VERSION:
        return RemoteProtocolError(
            ErrorCode.UNSUPPORTED_VERSION,
            f"protocol version {version} is not supported; this peer speaks version "
            f"{PROTOCOL_VERSION}",
            fatal=True,
        )
    return None


def check_header(magic: bytes, version: int) -> None:
    """Refuse a header that is not ours, or ours in a version this code does not speak."""
    error = header_error(magic, version)
    if error is not None:
        raise error


def sealed_flag_error(flags: int) -> RemoteProtocolError | None:
    """Why a frame header with bit 0 (``SEALED``) is refused (``None``: bit 0 is clear).

    The bit is set on the outer headers of a sealed TCP stream only (docs/protocol.md,
    sections 2 and 16.5), and it changes how the bytes after the header are read, so where a
    plain frame belongs it loses the framing: before the key handshake, on a session without
    sealed records, inside a record."""
    if flags & FLAG_MAC:
        return RemoteProtocolError(
            ErrorCode.MALFORMED,
            "a frame header with flags bit 0 (a sealed record) where a plain frame belongs: "
            "records exist only after the key handshake of a pre-shared-key session without TLS",
            fatal=True,
        )
    return None


def encode_run_into(codec: PacketCodec, buf: bytearray, channel: int, first_seq: int,
                    stamps: list[int], values: list[Any], max_batch: int, max_packet: int,
                    refused: list[tuple[int, int]]) -> int:
    """Append a channel's run of values to ``buf`` as TCP frames whose bodies are at most
    ``max_packet`` bytes (the receiver's limit), each a ``Batch`` of at most ``max_batch``
    values (a ``Value`` for one); return how many frames.

    Why by bytes too: a receiver refuses a longer frame from its header and ends the whole
    session (docs/protocol.md 2), so one burst of large values would end every channel.
    Cheap for the common case: a frame is encoded once and its length read; only a frame
    over the limit is taken back and its run cut at the share that fits by its average
    value (then 90 % of that, so the next try mostly fits), and the cut grows again after
    frames under half the limit (values of mixed sizes). A value whose ``Value`` frame is
    alone over the limit cannot go: it is left out and ``(seq, body bytes)`` appended to
    ``refused``, for the caller to count and say; the rest keep their sequence numbers.
    """
    n = len(values)
    start = len(buf)
    if n == 1:  # the common run (a value since the last round): one frame, one check
        codec.encode_frame_into(Value(channel, first_seq, stamps[0], values[0]), buf)
        body = len(buf) - start - _FRAME_HEAD
        if body <= max_packet:
            return 1
        del buf[start:]
        refused.append((first_seq, body))
        return 0
    frames = 0
    step = max(1, max_batch)
    i = 0
    while i < n:
        k = n - i if n - i < step else step
        start = len(buf)
        if k == 1:
            codec.encode_frame_into(Value(channel, first_seq + i, stamps[i], values[i]), buf)
        elif k == n:
            codec.encode_frame_into(Batch(channel, first_seq, stamps, values), buf)
        else:
            codec.encode_frame_into(Batch(channel, first_seq + i, stamps[i : i + k],
                                          values[i : i + k]), buf)
        body = len(buf) - start - _FRAME_HEAD
        if body <= max_packet:
            frames += 1
            i += k
            if step < max_batch and 2 * body <= max_packet:
                step = min(max_batch, 2 * step)
            continue
        del buf[start:]
        if k == 1:
            refused.append((first_seq + i, body))
            i += 1
        else:
            step = max(1, k * max_packet * 9 // (body * 10))
    return frames


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
        """Every packet the bytes so far complete, in order (a read chunk in one go).

        Raises the fault that broke the stream (a fatal :class:`RemoteProtocolError`), and
        then the packets completed before it in the same bytes are dropped: a receiver that
        must act on those first (the server) calls :meth:`feed_until_fault`.
        """
        packets, fault = self.feed_until_fault(data)
        if fault is not None:
            raise fault
        return packets

    def feed_until_fault(
        self, data: bytes
    ) -> tuple[list[Packet | Malformed], RemoteProtocolError | None]:
        """Every packet the bytes so far complete, in order, and the fault that broke the
        stream (``None`` while it holds).

        A header that loses the framing (bad magic or version, flags bit 0, a length over
        ``max_packet``) stops the decoding there: the packets before it are returned with
        it, so none is lost to the bytes that followed it in the same read; from then on
        every call returns no packet and the same fault. Per frame the loop makes one C call
        to decode (msgspec's, on a view of the buffer: no copy per frame); only a body that
        does not decode takes the slower path that grades its error
        (:meth:`PacketCodec.decode_body`).
        """
        if self._broken is not None:
            return [], self._broken
        buf = self._buf
        buf += data
        out: list[Packet | Malformed] = []
        append = out.append
        decode = self._codec.raw_decode
        unpack = FRAME_HEADER.unpack_from
        pos = 0
        size = len(buf)
        hsize = FRAME_HEADER.size
        limit = self._max
        fault: RemoteProtocolError | None = None
        view = memoryview(buf)
        try:
            while size - pos >= hsize:
                magic, version, flags, length = unpack(buf, pos)
                if magic != MAGIC or version != PROTOCOL_VERSION or flags & FLAG_MAC:
                    fault = header_error(magic, version) or sealed_flag_error(flags)
                    break
                if length > limit:
                    fault = RemoteProtocolError(
                        ErrorCode.TOO_LARGE,
                        f"frame of {length} bytes exceeds the limit of {limit} bytes",
                        fatal=True,
                    )
                    break
                end = pos + hsize + length
                if end > size:
                    break
                try:
                    append(decode(view[pos + hsize : end]))
                except Exception:  # msgspec's errors, graded in _invalid
                    append(self._invalid(view[pos + hsize : end]))
                pos = end
        finally:
            view.release()
        if fault is not None:
            self._broken = fault
            buf.clear()  # nothing after a fault is read: hold none of it
        elif pos:
            del buf[:pos]
        return out, fault

    def _invalid(self, body: memoryview) -> Packet | Malformed:
        """A body the fast decode refused, with its error graded as ``decode_body`` does."""
        try:
            return self._codec.decode_body(body)
        except RemoteProtocolError as exc:
            # A fresh error: the caught one's traceback and context hold a view of the
            # buffer, which would make ``del buf[:pos]`` in ``feed`` (and every later feed)
            # fail with BufferError.
            fresh = (PartlyMalformed(exc.bundle, exc.errors)
                     if isinstance(exc, PartlyMalformed)
                     else RemoteProtocolError(exc.code, exc.reason))
            fresh.tag, fresh.channel = exc.tag, exc.channel
        return Malformed(fresh)
