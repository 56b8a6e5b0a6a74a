"""A fatal header after good frames in one read: the frames come out first, then the fault.

``feed_until_fault`` is what a receiver that must act on every packet before the stream broke
calls (the server's TCP connection): the packets completed before the bad header, in order,
and the fault beside them, whatever the chunking. ``feed`` keeps its contract (it raises the
fault). Both decoders, plain frames and sealed records. No sockets.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rlbridge import ErrorCode, RemoteProtocolError
from rlbridge.wire import (
    FRAME_HEADER,
    MAGIC,
    PROTOCOL_VERSION,
    FrameDecoder,
    Heartbeat,
    Malformed,
    Packet,
    PacketCodec,
    Value,
)
from rlbridge.wire.records import (
    RECORD_MAX,
    RecordOpener,
    RecordSealer,
    SealedStreamDecoder,
    stream_sealers,
)
from rlbridge.wire.seal import TAG_SIZE, derive_keys

CODEC = PacketCodec()
LIMIT = 1000
GOOD: list[Packet] = [Value(1, i, i, float(i)) for i in range(4)] + [Heartbeat(5)]

#: Every header that loses the framing of a plain stream: (header, code, phrase of the reason).
BAD_HEADERS = [
    (FRAME_HEADER.pack(b"XX", PROTOCOL_VERSION, 0, 2), ErrorCode.MALFORMED, "bad magic b'XX'"),
    (FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION + 1, 0, 2), ErrorCode.UNSUPPORTED_VERSION,
     "not supported"),
    (FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0x01, 2), ErrorCode.MALFORMED, "flags bit 0"),
    (FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, LIMIT + 1), ErrorCode.TOO_LARGE,
     f"frame of {LIMIT + 1} bytes exceeds the limit of {LIMIT} bytes"),
]
BAD_IDS = ["magic", "version", "sealed-flag", "too-large"]


def good_frames(packets: list[Packet] = GOOD) -> bytes:
    buf = bytearray()
    for packet in packets:
        CODEC.encode_frame_into(packet, buf)
    return bytes(buf)


def assert_fault(fault: RemoteProtocolError | None, code: ErrorCode, phrase: str) -> None:
    assert fault is not None, "the bad header was taken"
    assert fault.fatal
    assert fault.code is code
    assert phrase in fault.reason


@pytest.mark.parametrize(("bad", "code", "phrase"), BAD_HEADERS, ids=BAD_IDS)
def test_frames_before_a_bad_header_come_out_with_its_fault(bad: bytes, code: ErrorCode,
                                                             phrase: str) -> None:
    decoder = FrameDecoder(CODEC, max_packet=LIMIT)
    packets, fault = decoder.feed_until_fault(good_frames() + bad + b"\x91\x0a")
    assert packets == GOOD
    assert_fault(fault, code, phrase)
    # The stream stays broken: nothing after the fault is read, and the same fault is told.
    again, same = decoder.feed_until_fault(good_frames())
    assert (again, same) == ([], fault)
    with pytest.raises(RemoteProtocolError) as raised:
        decoder.feed(good_frames())
    assert raised.value is fault


@pytest.mark.parametrize(("bad", "code", "phrase"), BAD_HEADERS, ids=BAD_IDS)
def test_feed_still_raises_the_fault(bad: bytes, code: ErrorCode, phrase: str) -> None:
    """``feed``'s contract is unchanged for the receivers that call it: the fault is raised."""
    with pytest.raises(RemoteProtocolError) as raised:
        FrameDecoder(CODEC, max_packet=LIMIT).feed(good_frames() + bad)
    assert_fault(raised.value, code, phrase)


def test_bad_bodies_before_the_fault_stay_graded_in_order() -> None:
    """A bad body before the bad header is still its own ``Malformed``, in its place."""
    bad_body = FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, 1) + b"\xc1"
    stream = good_frames(GOOD[:2]) + bad_body + good_frames(GOOD[2:]) + BAD_HEADERS[0][0]
    packets, fault = FrameDecoder(CODEC).feed_until_fault(stream)
    assert packets[:2] == GOOD[:2]
    assert isinstance(packets[2], Malformed)
    assert not packets[2].error.fatal
    assert packets[3:] == GOOD[2:]
    assert_fault(fault, ErrorCode.MALFORMED, "bad magic")


@settings(deadline=None, max_examples=100, suppress_health_check=[HealthCheck.too_slow])
@given(cuts=st.lists(st.integers(0, len(good_frames()) + 8), max_size=6),
       which=st.integers(0, len(BAD_HEADERS) - 1))
def test_any_chunking_gives_every_frame_then_the_fault(cuts: list[int], which: int) -> None:
    """Split anywhere (the bad header itself too): the same packets, then the same fault, and
    the fault comes with the chunk that completes the bad header."""
    bad, code, phrase = BAD_HEADERS[which]
    stream = good_frames() + bad
    bounds = [0, *sorted(set(cuts)), len(stream)]
    decoder = FrameDecoder(CODEC, max_packet=LIMIT)
    got: list[Packet | Malformed] = []
    fault: RemoteProtocolError | None = None
    for start, end in itertools.pairwise(bounds):
        packets, fault = decoder.feed_until_fault(stream[start:end])
        got += packets
        if fault is not None:
            assert end == len(stream), "the fault came before its header was whole"
            break
    assert got == GOOD
    assert_fault(fault, code, phrase)


# -- sealed records (docs/protocol.md 16.5) -------------------------------------------------


def sealed_pair() -> tuple[RecordSealer, SealedStreamDecoder]:
    keys = derive_keys(bytes(range(32)), b"salt", b"context")
    sealer, _ = stream_sealers(keys, server=False)
    _, opener_key = stream_sealers(keys, server=True)
    decoder = SealedStreamDecoder(CODEC, max_packet=LIMIT)
    decoder.install(RecordOpener(opener_key), strict=True)
    return sealer, decoder


def flipped(record: bytes) -> bytes:
    """A record with one bit of its tag changed (forged, or altered on the way)."""
    return record[:-1] + bytes([record[-1] ^ 1])


Seal = Callable[[bytes], bytes]
#: What ends a sealed stream after good records: (what follows them, code, phrase).
SEALED_FAULTS: list[tuple[Callable[[Seal], bytes], ErrorCode, str]] = [
    (lambda seal: FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, 2) + b"\x91\x0a",
     ErrorCode.AUTH_FAILED, "unsealed frame"),
    (lambda seal: FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0x01, RECORD_MAX + TAG_SIZE + 1),
     ErrorCode.AUTH_FAILED, "exceeds the limit"),
    (lambda seal: flipped(seal(good_frames())), ErrorCode.AUTH_FAILED, "does not open"),
    # The key's holder sent a bad frame inside a good record: the frames before it in that
    # record are as good as those of the records before.
    (lambda seal: seal(good_frames(GOOD[:2]) + FRAME_HEADER.pack(b"XX", PROTOCOL_VERSION, 0, 2)),
     ErrorCode.MALFORMED, "bad magic b'XX'"),
]


@pytest.mark.parametrize(("after", "code", "phrase"), SEALED_FAULTS,
                         ids=["plain-frame", "oversized-record", "forged-record",
                              "bad-frame-in-record"])
def test_records_before_a_bad_one_come_out_with_its_fault(after: Callable[[Seal], bytes],
                                                          code: ErrorCode, phrase: str) -> None:
    sealer, decoder = sealed_pair()
    seal = sealer.seal
    stream = seal(good_frames()) + seal(good_frames()) + after(seal)
    packets, fault = decoder.feed_until_fault(stream)
    expected = GOOD * 2 + (GOOD[:2] if code is ErrorCode.MALFORMED else [])
    assert packets == expected
    assert_fault(fault, code, phrase)
    assert decoder.feed_until_fault(b"") == ([], fault)
    with pytest.raises(RemoteProtocolError) as raised:
        decoder.feed(b"")
    assert raised.value is fault


def test_plain_frames_before_a_bad_header_on_a_stream_not_yet_sealed() -> None:
    """Before the key, the sealed decoder reads plain frames: the same rule holds there."""
    decoder = SealedStreamDecoder(CODEC, max_packet=LIMIT)
    packets, fault = decoder.feed_until_fault(good_frames() + BAD_HEADERS[3][0])
    assert packets == GOOD
    assert_fault(fault, ErrorCode.TOO_LARGE, "exceeds the limit")
