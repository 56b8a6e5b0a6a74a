"""The sans-IO codec: round trips, TCP framing in any chunking, and graded errors. No sockets."""

from __future__ import annotations

import contextlib
import struct
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rlbridge import ErrorCode, RemoteProtocolError
from rlbridge.wire import (
    DATAGRAM_HEADER,
    DEFAULT_MAX_PACKET,
    FRAME_HEADER,
    MAGIC,
    PROTOCOL_VERSION,
    AuthChallenge,
    AuthProof,
    Batch,
    Bundle,
    ChannelLoss,
    ConnectAck,
    ConnectError,
    Credit,
    Disconnect,
    Error,
    FrameDecoder,
    GoalCancel,
    GoalResult,
    GoalSend,
    Heartbeat,
    Hello,
    Limits,
    LossReport,
    Malformed,
    Packet,
    PacketCodec,
    RosLoss,
    ServiceCall,
    ServiceOffer,
    ServiceReply,
    ServiceRequest,
    ServiceResult,
    Stats,
    TopicAck,
    TopicClose,
    TopicConnect,
    TopicError,
    Value,
)

PROPS = settings(deadline=None, max_examples=150, suppress_health_check=[HealthCheck.too_slow])

# -- strategies ----------------------------------------------------------------------------

U16 = st.integers(0, 0xFFFF)
U32 = st.integers(0, 0xFFFF_FFFF)
U64 = st.integers(0, 2**64 - 1)
I64 = st.integers(-(2**63), 2**63 - 1)


def text(min_size: int = 0, max_size: int = 20) -> st.SearchStrategy[str]:
    return st.text(min_size=min_size, max_size=max_size)


#: Anything MessagePack carries and decodes back to an equal Python value.
scalars = (
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1)
    | st.floats(allow_nan=False) | text() | st.binary(max_size=20)
)
values: st.SearchStrategy[Any] = st.recursive(
    scalars,
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(text(max_size=6), children, max_size=4),
    max_leaves=12,
)


@st.composite
def batches(draw: st.DrawFn) -> Batch:
    n = draw(st.integers(0, 6))
    return Batch(
        draw(U32), draw(U64), draw(st.lists(I64, min_size=n, max_size=n)),
        draw(st.lists(values, min_size=n, max_size=n)),
    )


limits = st.builds(Limits, U32, U32, U32)
packet_strategies: dict[type, st.SearchStrategy[Any]] = {
    Hello: st.builds(Hello, U16, text(max_size=128), st.binary(max_size=64)),
    ConnectAck: st.builds(ConnectAck, U32, U64, U32, U32, limits, st.binary(max_size=64)),
    ConnectError: st.builds(ConnectError, U16, text(max_size=200)),
    TopicConnect: st.builds(
        TopicConnect, U32, st.sampled_from(["subscribe", "publish"]), text(1, 40),
        text(1, 40), st.none() | text(1, 30), st.sampled_from(["tcp", "udp"]), U32,
        st.sampled_from([None, "reliable", "best_effort"]), U16, U32, st.integers(0, 16),
        st.booleans(), st.booleans(), st.booleans(),
    ),
    TopicAck: st.builds(TopicAck, U32, text(1, 40), values,
                        st.none() | st.dictionaries(text(max_size=6), values, max_size=3),
                        st.none() | U64),
    TopicError: st.builds(TopicError, U32, U16, text(max_size=200)),
    TopicClose: st.builds(TopicClose, U32),
    Value: st.builds(Value, U32, U64, I64, values),
    Batch: batches(),
    Heartbeat: st.builds(Heartbeat, I64, I64),
    Disconnect: st.builds(Disconnect, U16, text(max_size=200)),
    Error: st.builds(Error, U16, text(max_size=200), st.none() | U32),
    Stats: st.builds(Stats, st.dictionaries(text(max_size=10), values, max_size=5)),
    AuthChallenge: st.builds(AuthChallenge, st.binary(min_size=16, max_size=16),
                             st.binary(min_size=32, max_size=32)),
    AuthProof: st.builds(AuthProof, st.binary(min_size=32, max_size=32)),
    Bundle: st.builds(Bundle, st.lists(st.builds(Value, U32, U64, I64, values) | batches(),
                                       max_size=5)),
    Credit: st.builds(Credit, U32, U64),
    LossReport: st.builds(LossReport, st.lists(
        st.builds(ChannelLoss, U32, U64, U64, U64, U64), max_size=5)),
}
#: Services, actions and ROS-side loss (tags 20-28).
fields = st.dictionaries(text(max_size=6), values, max_size=4)
packet_strategies.update({
    ServiceCall: st.builds(ServiceCall, U32, text(1, 40), text(1, 40), fields, U32),
    ServiceResult: st.builds(ServiceResult, U32, U16, st.none() | fields, text(max_size=100)),
    ServiceOffer: st.builds(ServiceOffer, U32, text(1, 40), text(1, 40)),
    ServiceRequest: st.builds(ServiceRequest, U32, U64, fields),
    ServiceReply: st.builds(ServiceReply, U32, U64, U16, st.none() | fields,
                            text(max_size=100)),
    GoalSend: st.builds(GoalSend, U32, text(1, 40), text(1, 40), fields, U32),
    GoalCancel: st.builds(GoalCancel, U32),
    GoalResult: st.builds(GoalResult, U32, U16, st.none() | fields, text(max_size=100)),
    RosLoss: st.builds(RosLoss, U32, U64),
})
PACKET_TYPES: tuple[type, ...] = Packet.__args__  # type: ignore[attr-defined]
packets: st.SearchStrategy[Packet] = st.one_of(*packet_strategies.values())


def test_every_packet_type_has_a_strategy() -> None:
    """A packet type added to the union without a round-trip strategy fails here."""
    assert set(PACKET_TYPES) == set(packet_strategies)


#: One of each packet type, for framing tests.
SAMPLES: list[Packet] = [
    Hello(PROTOCOL_VERSION, "client", b"secret"),
    ConnectAck(7, 2**64 - 1, 200, 600, Limits(1 << 20, 256, 4096), b"chal"),
    ConnectError(int(ErrorCode.LIMIT), "too many sessions"),
    TopicConnect(3, "publish", "/cmd_vel", "geometry_msgs/msg/Twist", None, "udp", 8,
                 "best_effort", 5, 100, 2),
    TopicAck(3, "geometry_msgs/msg/Twist", {"linear": {"x": 0.0}}),
    TopicError(4, int(ErrorCode.UNKNOWN_TYPE), "no such type"),
    TopicClose(3),
    Value(1, 42, -5, 1.5),
    Batch(1, 43, [1, 2, 3], [2.5, "x", None]),
    Heartbeat(123456789, 123),
    Disconnect(30, "bye"),
    Error(int(ErrorCode.BAD_VALUE), "not a float", 9),
    Stats({"server": {"sessions_opened": 3}}),
    AuthChallenge(b"n" * 16, b"p" * 32),
    AuthProof(b"q" * 32),
    Bundle([Value(1, 44, -5, 1.5), Batch(2, 0, [1, 2], [None, "y"])]),
    ServiceCall(1, "/arm/enable", "std_srvs/srv/SetBool", {"data": True}, 2000),
    ServiceResult(1, 0, {"success": True, "message": ""}),
    ServiceOffer(5, "/home", "std_srvs/srv/Trigger"),
    ServiceRequest(5, 9, {}),
    ServiceReply(5, 9, 0, {"success": True, "message": "homed"}),
    GoalSend(6, "/fibonacci", "test_msgs/action/Fibonacci", {"order": 5}),
    GoalCancel(6),
    GoalResult(6, 4, {"sequence": [0, 1, 1, 2, 3, 5]}),
    RosLoss(2, 17),
]


def frame(body: bytes, *, magic: bytes = MAGIC, version: int = PROTOCOL_VERSION,
          length: int | None = None) -> bytes:
    """A TCP frame around an arbitrary body (for building invalid streams)."""
    return FRAME_HEADER.pack(magic, version, 0, len(body) if length is None else length) + body


def body(*fields: Any) -> bytes:
    return msgspec.msgpack.encode(list(fields))


# -- round trips ---------------------------------------------------------------------------


@PROPS
@given(packets)
def test_frame_round_trip(packet: Packet) -> None:
    codec = PacketCodec()
    data = codec.encode_frame(packet)
    assert data[:2] == MAGIC
    assert FRAME_HEADER.unpack_from(data)[3] == len(data) - FRAME_HEADER.size
    decoded = FrameDecoder(codec).feed(data)
    assert decoded == [packet]
    assert type(decoded[0]) is type(packet)


@PROPS
@given(packets, U64, st.integers(0, 255))
def test_datagram_round_trip(packet: Packet, token: int, flags: int) -> None:
    codec = PacketCodec()
    data = codec.encode_datagram(packet, token, flags)
    assert len(data) == DATAGRAM_HEADER.size + len(msgspec.msgpack.encode(packet))
    assert codec.decode_datagram(data) == (flags, token, packet)


@PROPS
@given(st.lists(packets, min_size=1, max_size=8))
def test_encode_frame_into_appends_the_same_frames(batch: list[Packet]) -> None:
    codec = PacketCodec()
    buf = bytearray(b"prefix")
    for packet in batch:
        codec.encode_frame_into(packet, buf)
    assert bytes(buf) == b"prefix" + b"".join(codec.encode_frame(p) for p in batch)


# -- TCP framing in any chunking -----------------------------------------------------------


def stream_of(batch: list[Packet]) -> bytes:
    codec = PacketCodec()
    return b"".join(codec.encode_frame(p) for p in batch)


def test_split_at_every_byte_boundary() -> None:
    data = stream_of(SAMPLES)
    for cut in range(len(data) + 1):
        decoder = FrameDecoder()
        got = decoder.feed(data[:cut]) + decoder.feed(data[cut:])
        assert got == SAMPLES, f"split at byte {cut}"
        assert decoder.buffered == 0


def test_one_byte_at_a_time() -> None:
    codec = PacketCodec()
    ends, total = [], 0
    for packet in SAMPLES:
        total += len(codec.encode_frame(packet))
        ends.append(total)
    data = stream_of(SAMPLES)
    decoder = FrameDecoder()
    got: list[Packet | Malformed] = []
    for i in range(len(data)):
        got += decoder.feed(data[i : i + 1])
        fed = i + 1
        complete = [end for end in ends if end <= fed]
        # Each packet comes out on its frame's last byte; the partial frame waits.
        assert len(got) == len(complete)
        assert decoder.buffered == fed - (complete[-1] if complete else 0)
    assert got == SAMPLES
    assert decoder.buffered == 0


def test_coalesced_frames_in_one_feed() -> None:
    many = [Value(1, i, i, float(i)) for i in range(2000)] + SAMPLES
    decoder = FrameDecoder()
    assert decoder.feed(b"") == []
    assert decoder.feed(stream_of(many)) == many
    assert decoder.buffered == 0


def test_bad_bodies_among_good_frames_cost_only_themselves() -> None:
    """One read chunk: every good frame decodes, each bad body becomes a Malformed with the
    error ``decode_body`` gives it alone (tag and channel salvaged), and the decoder's buffer
    is not held by any of them (the next feed works)."""
    codec = PacketCodec()

    def frame(body: bytes) -> bytes:
        return FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, len(body)) + body

    bad_bodies = [b"\xc1", msgspec.msgpack.encode([2, 7, "not a seq", 0, 1.0]),
                  b"\xa2\xff\xfe"]
    good = [Value(1, i, i, float(i)) for i in range(3)]
    chunk = b"".join(codec.encode_frame(g) + frame(b) for g, b in zip(good, bad_bodies,
                                                                      strict=True))
    decoder = FrameDecoder(codec)
    got = decoder.feed(chunk)
    assert [g for g in got if not isinstance(g, Malformed)] == good
    bad = [g for g in got if isinstance(g, Malformed)]
    assert len(bad) == 3
    for item, body in zip(bad, bad_bodies, strict=True):
        with pytest.raises(RemoteProtocolError) as alone:
            codec.decode_body(body)
        assert (item.error.code, item.error.reason) == (alone.value.code, alone.value.reason)
        assert (item.error.tag, item.error.channel) == (alone.value.tag, alone.value.channel)
    assert bad[1].error.channel == 7
    assert decoder.feed(codec.encode_frame(good[0])) == [good[0]]
    assert decoder.buffered == 0


@PROPS
@given(st.lists(packets, min_size=1, max_size=6), st.data())
def test_any_chunking_gives_the_same_packets(batch: list[Packet], data: st.DataObject) -> None:
    stream = stream_of(batch)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    decoder = FrameDecoder()
    got: list[Packet | Malformed] = []
    for start, end in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        got += decoder.feed(stream[start:end])
    assert got == batch


def test_partial_header_is_held_until_complete() -> None:
    data = PacketCodec().encode_frame(Heartbeat(1, 2))
    decoder = FrameDecoder()
    assert decoder.feed(data[:3]) == []
    assert decoder.buffered == 3
    assert decoder.feed(data[3:]) == [Heartbeat(1, 2)]


# -- random bytes raise only the protocol's own error --------------------------------------


def feed_all(decoder: FrameDecoder, chunks: list[bytes]) -> None:
    """Feed until the decoder refuses; any exception but RemoteProtocolError fails the test."""
    refused: RemoteProtocolError | None = None
    for chunk in chunks:
        try:
            out = decoder.feed(chunk)
        except RemoteProtocolError as exc:
            refused = exc
            break
        for item in out:
            assert isinstance(item, (Malformed, *PACKET_TYPES))
            if isinstance(item, Malformed):
                assert isinstance(item.error, RemoteProtocolError)
                assert not item.error.fatal
    if refused is not None:
        assert refused.fatal, "a refused stream must be fatal"
        with pytest.raises(RemoteProtocolError):
            decoder.feed(b"")  # and it stays refused


@PROPS
@given(st.lists(st.binary(max_size=64), max_size=6))
def test_random_bytes_into_frame_decoder(chunks: list[bytes]) -> None:
    feed_all(FrameDecoder(max_packet=4096), chunks)


@PROPS
@given(st.lists(st.binary(max_size=64), min_size=1, max_size=4))
def test_random_bodies_in_valid_frames(bodies: list[bytes]) -> None:
    """Valid headers, random bodies: the body decoder sees the garbage, not the header check."""
    decoder = FrameDecoder()
    out = decoder.feed(b"".join(frame(b) for b in bodies))
    assert len(out) == len(bodies)
    for item in out:
        if isinstance(item, Malformed):
            assert item.error.code is ErrorCode.MALFORMED


@PROPS
@given(st.sampled_from(SAMPLES), st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)),
                                          min_size=1, max_size=4))
def test_mutated_frames_raise_only_protocol_errors(packet: Packet,
                                                   edits: list[tuple[int, int]]) -> None:
    data = bytearray(PacketCodec().encode_frame(packet))
    for pos, byte in edits:
        data[pos % len(data)] = byte
    feed_all(FrameDecoder(max_packet=4096), [bytes(data), PacketCodec().encode_frame(packet)])


@PROPS
@given(st.binary(max_size=80))
def test_random_datagrams(data: bytes) -> None:
    codec = PacketCodec()
    with contextlib.suppress(RemoteProtocolError):
        codec.decode_datagram(data)


@PROPS
@given(U64, st.binary(max_size=80))
def test_random_datagram_bodies(token: int, payload: bytes) -> None:
    data = DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, token) + payload
    refused: RemoteProtocolError | None = None
    try:
        _flags, got_token, _packet = PacketCodec().decode_datagram(data)
    except RemoteProtocolError as exc:
        refused = exc
    else:
        assert got_token == token
    if refused is not None:
        assert refused.code is ErrorCode.MALFORMED
        assert not refused.fatal


# -- fatal header errors -------------------------------------------------------------------


def assert_broken(decoder: FrameDecoder, code: ErrorCode, *phrases: str) -> None:
    """The decoder refuses now, with a clear message, and keeps refusing valid frames."""
    good = PacketCodec().encode_frame(Heartbeat(1))
    with pytest.raises(RemoteProtocolError) as again:
        decoder.feed(good)
    assert again.value.code is code
    assert again.value.fatal
    for phrase in phrases:
        assert phrase in again.value.reason


def test_bad_magic_is_fatal() -> None:
    decoder = FrameDecoder()
    with pytest.raises(RemoteProtocolError) as exc:
        decoder.feed(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
    assert exc.value.fatal
    assert exc.value.code is ErrorCode.MALFORMED
    assert "bad magic b'GE'" in exc.value.reason
    assert "rlbridge protocol" in exc.value.reason
    assert_broken(decoder, ErrorCode.MALFORMED, "bad magic")


def test_bad_magic_after_good_frames_is_fatal() -> None:
    decoder = FrameDecoder()
    good = PacketCodec().encode_frame(Heartbeat(5))
    with pytest.raises(RemoteProtocolError):
        decoder.feed(good + b"XX" + good[2:])
    assert_broken(decoder, ErrorCode.MALFORMED, "bad magic b'XX'")


def test_unsupported_version_is_fatal() -> None:
    decoder = FrameDecoder()
    with pytest.raises(RemoteProtocolError) as exc:
        decoder.feed(frame(body(10, 1, 0), version=PROTOCOL_VERSION + 1))
    assert exc.value.fatal
    assert exc.value.code is ErrorCode.UNSUPPORTED_VERSION
    assert f"protocol version {PROTOCOL_VERSION + 1} is not supported" in exc.value.reason
    assert f"speaks version {PROTOCOL_VERSION}" in exc.value.reason
    assert_broken(decoder, ErrorCode.UNSUPPORTED_VERSION, "not supported")


def test_oversized_length_is_refused_from_the_header_alone() -> None:
    decoder = FrameDecoder(max_packet=1000)
    header = FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, 1001)
    with pytest.raises(RemoteProtocolError) as exc:
        decoder.feed(header)  # no body sent: refused before buffering it
    assert exc.value.fatal
    assert exc.value.code is ErrorCode.TOO_LARGE
    assert exc.value.reason == "frame of 1001 bytes exceeds the limit of 1000 bytes"
    assert_broken(decoder, ErrorCode.TOO_LARGE, "1001")


def test_default_limit_and_exact_limit() -> None:
    decoder = FrameDecoder()
    with pytest.raises(RemoteProtocolError) as exc:
        decoder.feed(FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, DEFAULT_MAX_PACKET + 1))
    assert exc.value.code is ErrorCode.TOO_LARGE
    # A frame of exactly the limit is accepted.
    payload = Value(1, 0, 0, "x" * 200)
    size = len(msgspec.msgpack.encode(payload))
    assert FrameDecoder(max_packet=size).feed(PacketCodec().encode_frame(payload)) == [payload]


def test_datagram_header_errors() -> None:
    codec = PacketCodec()
    with pytest.raises(RemoteProtocolError, match="shorter than the 12-byte header") as short:
        codec.decode_datagram(b"RB\x01")
    assert short.value.code is ErrorCode.MALFORMED
    good = codec.encode_datagram(Heartbeat(1), 99)
    with pytest.raises(RemoteProtocolError, match="bad magic") as magic:
        codec.decode_datagram(b"XX" + good[2:])
    assert magic.value.code is ErrorCode.MALFORMED
    with pytest.raises(RemoteProtocolError, match="version 9 is not supported") as version:
        codec.decode_datagram(good[:2] + bytes([9]) + good[3:])
    assert version.value.code is ErrorCode.UNSUPPORTED_VERSION


# -- invalid bodies in good frames cost only that packet -----------------------------------

MALFORMED_BODIES = {
    "batch stamps and values differ": (body(9, 1, 0, [1, 2], [1.0]), "1 values but 2 stamps"),
    "unknown tag": (body(99, 1), "Invalid value 99"),
    "string where an int goes": (body(8, "one", 0, 0, 1.0), "Expected `int`, got `str`"),
    "missing fields": (body(8, 1), "Expected `array` of at least length"),
    "negative unsigned": (body(7, -1), "Expected `int` >= 0"),
    "bad literal": (body(4, 1, "sideways", "/t", "std_msgs/msg/Float64"), "sideways"),
    "empty topic": (body(4, 1, "publish", "", "std_msgs/msg/Float64"), "length >= 1"),
    "not an array": (msgspec.msgpack.encode({"tag": 8}), "Expected `array`"),
    "not msgpack": (b"\xc1", "not a packet"),
    "truncated msgpack": (body(8, 1, 2, 3, "abcdef")[:-3], "not a packet"),
    "invalid utf-8": (b"\x93\x03\x01\xa2\xff\xfe", "UTF-8"),
    "nested without bound": (b"\x95\x08\x01\x00\x00" + b"\x91" * 200_000 + b"\xc0",
                             "nested too deeply"),
}


@pytest.mark.parametrize("name", sorted(MALFORMED_BODIES))
def test_malformed_body_then_next_frame(name: str) -> None:
    bad, phrase = MALFORMED_BODIES[name]
    codec = PacketCodec()
    before, after = Heartbeat(1), Value(2, 3, 4, "next")
    decoder = FrameDecoder()
    out = decoder.feed(codec.encode_frame(before) + frame(bad) + codec.encode_frame(after))
    assert len(out) == 3
    assert out[0] == before
    assert out[2] == after
    bad_entry = out[1]
    assert isinstance(bad_entry, Malformed)
    assert bad_entry.error.code is ErrorCode.MALFORMED
    assert not bad_entry.error.fatal
    assert phrase in bad_entry.error.reason
    # The decoder goes on, in later feeds too.
    assert decoder.feed(codec.encode_frame(after)) == [after]
    assert decoder.buffered == 0


@pytest.mark.parametrize("name", sorted(MALFORMED_BODIES))
def test_malformed_datagram_body(name: str) -> None:
    bad, phrase = MALFORMED_BODIES[name]
    with pytest.raises(RemoteProtocolError) as exc:
        PacketCodec().decode_datagram(DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, 5) + bad)
    assert exc.value.code is ErrorCode.MALFORMED
    assert not exc.value.fatal
    assert phrase in exc.value.reason


def test_malformed_keeps_what_could_be_salvaged() -> None:
    """Tag and channel of an invalid ``[tag, channel, ...]`` body survive, in both framings."""
    bad = body(8, 5, "not a seq", 0, 1.0)
    (entry,) = FrameDecoder().feed(frame(bad))
    assert isinstance(entry, Malformed)
    assert (entry.error.tag, entry.error.channel) == (8, 5)
    with pytest.raises(RemoteProtocolError) as exc:
        PacketCodec().decode_datagram(DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, 77) + bad)
    assert (exc.value.tag, exc.value.channel, exc.value.token) == (8, 5, 77)
    (nothing,) = FrameDecoder().feed(frame(b"\xc1"))
    assert isinstance(nothing, Malformed)
    assert (nothing.error.tag, nothing.error.channel) == (None, None)


def test_malformed_body_split_byte_by_byte() -> None:
    codec = PacketCodec()
    stream = frame(body(99, 1)) + codec.encode_frame(Heartbeat(7))
    decoder = FrameDecoder()
    got: list[Packet | Malformed] = []
    for i in range(len(stream)):
        got += decoder.feed(stream[i : i + 1])
    assert [type(g) for g in got] == [Malformed, Heartbeat]


def test_batch_constructor_refuses_mismatch() -> None:
    with pytest.raises(ValueError, match="batch has 1 values but 2 stamps"):
        Batch(1, 0, [1, 2], [1.0])


def test_unknown_trailing_fields_are_ignored() -> None:
    """Forward compatibility: a newer peer may append fields."""
    decoder = FrameDecoder()
    assert decoder.feed(frame(body(10, 5, 6, 7, 8, 9, "future", 1))) == [Heartbeat(5, 6, 7, 8, 9)]


def test_header_layout() -> None:
    data = PacketCodec().encode_frame(TopicClose(1))
    magic, version, flags, length = struct.unpack(">2sBBI", data[:8])
    assert (magic, version, flags, length) == (b"RB", PROTOCOL_VERSION, 0, len(data) - 8)
    dgram = PacketCodec().encode_datagram(TopicClose(1), 0x0102030405060708, flags=1)
    assert dgram[:12] == b"RB" + bytes([PROTOCOL_VERSION, 1]) + bytes(range(1, 9))
