"""Fuzz the sans-IO decoder: TCP framing, packet bodies, sealed datagrams and sealed records.

Run: ``python fuzz/fuzz_decoder.py fuzz/corpus/decoder -max_total_time=60`` (atheris, libFuzzer
flags). Invariants: only the protocol's own :class:`RemoteProtocolError` ever escapes, every
decoded packet re-encodes, and the decoder never buffers more than one frame's worth of bytes.
``one_input`` is importable without atheris (the test suite replays the corpus through it).
"""

from __future__ import annotations

import contextlib

from _atheris import fuzz, instrumented

with instrumented(__name__ == "__main__"):
    from rlbridge.wire import FrameDecoder, Malformed, PacketCodec, RemoteProtocolError
    from rlbridge.wire.auth import ReplayWindow, SealedCodec
    from rlbridge.wire.codec import FRAME_HEADER
    from rlbridge.wire.records import RECORD_MAX, RecordOpener, SealedStreamDecoder

MAX_PACKET = 4096
KEY_A, KEY_B = bytes(32), bytes(range(32))
CODEC = PacketCodec()


def _chunks(data: bytes) -> list[bytes]:
    """Split the input where the first byte says, so the fuzzer also explores chunking."""
    if not data:
        return []
    step = data[0] % 17 + 1
    body = data[1:]
    return [body[i : i + step] for i in range(0, len(body), step)]


def one_input(data: bytes) -> None:
    decoder = FrameDecoder(CODEC, MAX_PACKET)
    try:
        for chunk in _chunks(data):
            for packet in decoder.feed(chunk):
                if not isinstance(packet, Malformed):
                    CODEC.encode_frame(packet)  # what decodes must encode again
            assert decoder.buffered <= MAX_PACKET + 2 * FRAME_HEADER.size, decoder.buffered
    except RemoteProtocolError as exc:
        if not exc.fatal:
            raise AssertionError("a non-fatal error must come back as Malformed") from exc
    # The same bytes as a sealed TCP stream (records under KEY_B, as the corpus seals them):
    # only protocol errors escape, and a fatal one leaves the decoder refusing everything.
    stream = SealedStreamDecoder(CODEC, MAX_PACKET)
    stream.install(RecordOpener(KEY_B), strict=bool(data[:1]) and data[0] & 1 == 1)
    try:
        for chunk in _chunks(data):
            stream.feed(chunk)
            assert stream.buffered <= RECORD_MAX + MAX_PACKET + 4 * FRAME_HEADER.size + 16
    except RemoteProtocolError as exc:
        if not exc.fatal:
            raise AssertionError("record and framing errors must end the stream") from exc
    for codec in (CODEC, SealedCodec(KEY_A, KEY_B)):
        with contextlib.suppress(RemoteProtocolError):
            codec.decode_datagram(data)
    window = ReplayWindow(64)
    for i in range(0, len(data) - 1, 2):
        window.check(int.from_bytes(data[i : i + 2], "big"))


if __name__ == "__main__":
    fuzz(one_input)
