"""Bundles, sans-IO: the packer's datagrams round-trip, fit their budget, keep every part's
order, and a bundle with invalid parts gives back the valid ones. No sockets."""

from __future__ import annotations

from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rlbridge.wire import DATAGRAM_HEADER, Batch, Bundle, PacketCodec, Value
from rlbridge.wire.auth import SEAL_OVERHEAD, SealedCodec
from rlbridge.wire.bundle import BATCH_TAG, VALUE_TAG, DatagramPacker, Part, as_packet
from rlbridge.wire.codec import FLAG_BUNDLES, FLAG_MAC, PartlyMalformed, peek_header

PROPS = settings(deadline=None, max_examples=150, suppress_health_check=[HealthCheck.too_slow])
TOKEN = 0x0123456789ABCDEF
KEY_A, KEY_B = bytes(range(32)), bytes(32)

values = st.floats(allow_nan=False) | st.integers(-(2**63), 2**63 - 1) | st.text(max_size=60)


@st.composite
def parts(draw: st.DrawFn) -> Value | Batch:
    channel = draw(st.integers(0, 20))
    seq = draw(st.integers(0, 2**40))
    if draw(st.booleans()):
        return Value(channel, seq, draw(st.integers(0, 2**62)), draw(values))
    vals = draw(st.lists(values, max_size=80))
    return Batch(channel, seq, [draw(st.integers(0, 2**62))] * len(vals), vals)


def flatten(packets: list[Any]) -> list[tuple[int, int, Any]]:
    """(channel, seq, value) of every value, bundles opened, in order."""
    out: list[tuple[int, int, Any]] = []
    for p in packets:
        if isinstance(p, Bundle):
            out += flatten(list(p.parts))
        elif isinstance(p, Value):
            out.append((p.channel, p.seq, p.value))
        else:
            out += [(p.channel, p.first_seq + i, v) for i, v in enumerate(p.values)]
    return out


@PROPS
@given(st.lists(parts(), max_size=30), st.integers(200, 1500), st.booleans(), st.booleans())
def test_packed_datagrams_round_trip_within_budget(packets: list[Value | Batch], budget: int,
                                                   bundles: bool, sealed: bool) -> None:
    sender = SealedCodec(KEY_A, KEY_B) if sealed else PacketCodec()
    receiver = SealedCodec(KEY_B, KEY_A) if sealed else PacketCodec()
    out: list[bytes] = []
    packer = DatagramPacker(sender, TOKEN, budget, out.append, limit=65507, bundles=bundles,
                            flags=FLAG_BUNDLES)
    for packet in packets:
        assert packer.add(packet) == 0
    packer.flush()
    assert packer.pending == 0
    decoded = []
    for datagram in out:
        flags, token, packet = receiver.decode_datagram(datagram)
        assert token == TOKEN
        assert flags & FLAG_BUNDLES
        decoded.append(packet)
        alone = isinstance(packet, Value) or len(getattr(packet, "values", ())) == 1
        assert len(datagram) <= budget or alone  # only a single value may exceed it
        if not bundles:
            assert not isinstance(packet, Bundle)
        if isinstance(packet, Bundle):
            assert len(packet.parts) >= 2
    assert flatten(decoded) == flatten(list(packets))
    assert packer.datagrams == len(out)


def test_one_round_of_small_parts_is_one_datagram_byte_for_byte_a_bundle() -> None:
    """The assembled bytes are exactly what encoding a Bundle packet gives (fixarray, and
    array16 past 15 parts); a round of one part is that part alone."""
    codec = PacketCodec()
    for n in (2, 15, 16, 40):
        out: list[bytes] = []
        packer = DatagramPacker(codec, TOKEN, 1400, out.append)
        packets = [Value(i, 7, 1_700_000_000_000_000_000, float(i)) for i in range(n)]
        for p in packets:
            packer.add(p)
        packer.flush()
        assert out == [codec.encode_datagram(Bundle(packets), TOKEN)]
    out = []
    packer = DatagramPacker(codec, TOKEN, 1400, out.append)
    packer.add(Value(3, 7, 1, 1.5))
    packer.flush()
    assert out == [codec.encode_datagram(Value(3, 7, 1, 1.5), TOKEN)]


def as_tuple(packet: Value | Batch) -> tuple[Any, ...]:
    """The tuple form of a part, as the SDK's send round makes it."""
    if isinstance(packet, Value):
        return (VALUE_TAG, packet.channel, packet.seq, packet.stamp_ns, packet.value)
    return (BATCH_TAG, packet.channel, packet.first_seq, packet.stamps, packet.values)


@pytest.mark.parity("rlbridge.wire.bundle.DatagramPacker.send_parts")
@PROPS
@given(st.lists(parts(), min_size=1, max_size=30), st.integers(200, 1500), st.booleans())
def test_a_round_in_one_call_is_byte_for_byte_the_bundle_of_its_parts(
        packets: list[Value | Batch], budget: int, tuples: bool) -> None:
    """``send_parts`` (one msgspec call) sends exactly the datagram of ``Bundle(parts)`` (of
    the part itself when alone) when ``add`` would make that one datagram; otherwise it sends
    nothing (and ``add`` makes several)."""
    codec = PacketCodec()
    out: list[bytes] = []
    packer = DatagramPacker(codec, TOKEN, budget, out.append, limit=65507, flags=FLAG_BUNDLES)
    round_: list[Part] = [as_tuple(p) if tuples else p for p in packets]
    expected = codec.encode_datagram(packets[0] if len(packets) == 1 else Bundle(packets),
                                     TOKEN, FLAG_BUNDLES)
    if packer.send_parts(round_):
        assert out == [expected] == one_by_one(packets, budget)
        assert (packer.datagrams, packer.bundles_sent) == (1, int(len(packets) > 1))
    else:
        assert len(one_by_one(packets, budget)) > 1
        assert (out, packer.datagrams) == ([], 0)
    assert round_ == [as_tuple(p) if tuples else p for p in packets]  # parts untouched


def one_by_one(packets: list[Value | Batch], budget: int) -> list[bytes]:
    """The datagrams ``add`` and ``flush`` make of one round."""
    out: list[bytes] = []
    packer = DatagramPacker(PacketCodec(), TOKEN, budget, out.append, limit=65507,
                            flags=FLAG_BUNDLES)
    for p in packets:
        assert packer.add(p) == 0
    packer.flush()
    return out


@pytest.mark.parametrize("n", [2, 15, 16, 40])
def test_a_round_in_one_call_reserves_what_add_reserves(n: int) -> None:
    """``add`` reserves an array16 header for a bundle; a fixarray (< 16 parts) is two bytes
    shorter. A round that fits only by those two bytes goes as ``add`` sends it: split."""
    packets: list[Value | Batch] = [Value(c, 1, 2, float(c)) for c in range(n)]
    size = len(PacketCodec().encode_datagram(Bundle(packets), TOKEN, FLAG_BUNDLES))
    spare = 2 if n < 16 else 0
    for budget in range(size - 1, size + spare + 2):
        out: list[bytes] = []
        packer = DatagramPacker(PacketCodec(), TOKEN, budget, out.append, flags=FLAG_BUNDLES)
        sent = packer.send_parts([as_tuple(p) for p in packets])
        assert sent == (budget >= size + spare)
        expected = one_by_one(packets, budget)
        assert len(expected) == (1 if sent else 2)
        if sent:
            assert out == expected


@pytest.mark.parametrize("n", [2, 15, 16, 40])
def test_a_sealed_round_in_one_call_splits_where_add_splits(n: int) -> None:
    """The sealed one-call way makes the datagrams ``add`` makes, at every budget around the
    one where ``add`` stops splitting the round (the same reserve for the array header)."""
    packets: list[Value | Batch] = [Value(c, 1, 2, float(c)) for c in range(n)]
    whole: list[bytes] = []
    DatagramPacker(SealedCodec(KEY_A, KEY_B), TOKEN, 65507, whole.append,
                   flags=FLAG_BUNDLES).send_parts([as_tuple(p) for p in packets])
    size = len(whole[0])
    outcomes = set()
    for budget in range(size - 8, size + 80):
        by_add: list[bytes] = []
        packer = DatagramPacker(SealedCodec(KEY_A, KEY_B), TOKEN, budget, by_add.append,
                                limit=65507, flags=FLAG_BUNDLES)
        for p in packets:
            assert packer.add(p) == 0
        packer.flush()
        out: list[bytes] = []
        sent = DatagramPacker(SealedCodec(KEY_A, KEY_B), TOKEN, budget, out.append,
                              limit=65507, flags=FLAG_BUNDLES).send_parts(
                                  [as_tuple(p) for p in packets])
        assert sent == (len(by_add) == 1), budget
        outcomes.add(sent)
        if sent:
            assert [len(d) for d in out] == [len(d) for d in by_add]
    assert outcomes == {False, True}  # the budgets spanned the split


def test_a_round_in_one_call_needs_a_codec_that_bundles() -> None:
    out: list[bytes] = []
    round_: list[Part] = [as_tuple(Value(1, 0, 0, 1.0)), as_tuple(Value(2, 0, 0, 2.0))]
    packer = DatagramPacker(PacketCodec(), TOKEN, 1400, out.append, bundles=False)
    assert packer.one_call is False
    assert packer.send_parts(round_) is False
    assert out == []
    assert DatagramPacker(PacketCodec(), TOKEN, 1400, out.append).send_parts([]) is False


def test_a_sealed_round_in_one_call_is_one_sealed_bundle() -> None:
    """A sealing codec takes the one-call way too: the round's one encoding, sealed once."""
    out: list[bytes] = []
    round_: list[Part] = [as_tuple(Value(1, 0, 0, 1.0)), as_tuple(Value(2, 0, 0, 2.0))]
    packer = DatagramPacker(SealedCodec(KEY_A, KEY_B), TOKEN, 1400, out.append,
                            flags=FLAG_BUNDLES)
    packer.add(Value(3, 0, 0, 3.0))  # added before the round: goes first, alone
    assert packer.one_call
    assert packer.send_parts(round_)
    assert packer.send_parts(round_[:1])
    receiver = SealedCodec(KEY_B, KEY_A)
    got = [receiver.decode_datagram(d) for d in out]
    assert [flags & FLAG_MAC for flags, _t, _p in got] == [FLAG_MAC] * 3
    assert [p for _f, _t, p in got] == [Value(3, 0, 0, 3.0),
                                         Bundle([Value(1, 0, 0, 1.0), Value(2, 0, 0, 2.0)]),
                                         Value(1, 0, 0, 1.0)]
    assert (packer.datagrams, packer.bundles_sent) == (3, 1)
    # A round too large for the budget together is refused whole (then added part by part).
    small = DatagramPacker(SealedCodec(KEY_A, KEY_B), TOKEN, 60, out.append)
    assert small.send_parts(round_) is False


def test_parts_added_before_a_round_in_one_call_go_first() -> None:
    codec = PacketCodec()
    out: list[bytes] = []
    packer = DatagramPacker(codec, TOKEN, 1400, out.append)
    packer.add(Value(1, 0, 0, 1.0))
    assert packer.send_parts([as_tuple(Value(2, 0, 0, 2.0))])
    assert [codec.decode_datagram(d)[2] for d in out] == [Value(1, 0, 0, 1.0),
                                                           Value(2, 0, 0, 2.0)]


def test_as_packet_gives_the_packet_a_part_stands_for() -> None:
    value, batch = Value(1, 2, 3, 4.0), Batch(5, 6, [7, 8], [9.0, 10.0])
    assert [as_packet(as_tuple(value)), as_packet(as_tuple(batch))] == [value, batch]
    assert as_packet(value) is value
    with pytest.raises(ValueError, match="not a value part"):
        as_packet((32, []))


def test_a_value_too_large_is_refused_and_counted() -> None:
    out: list[bytes] = []
    packer = DatagramPacker(PacketCodec(), TOKEN, 200, out.append)  # limit = budget
    assert packer.add(Value(1, 0, 0, "x" * 300)) == 1
    assert packer.add(Batch(1, 1, [0, 0], ["x" * 300, "y"])) == 1  # the small one goes
    packer.flush()
    assert [PacketCodec().decode_datagram(d)[2] for d in out] == [Batch(1, 2, [0], ["y"])]


def test_discard_counts_values_not_parts() -> None:
    packer = DatagramPacker(PacketCodec(), TOKEN, 1400, lambda d: None)
    packer.add(Value(1, 0, 0, 1.0))
    packer.add(Batch(2, 0, [0, 0, 0], [1.0, 2.0, 3.0]))
    assert (packer.pending, packer.discard(), packer.pending) == (2, 4, 0)


def body(*fields: Any) -> bytes:
    return msgspec.msgpack.encode(list(fields))


def test_partly_malformed_bundle_keeps_its_valid_parts() -> None:
    codec = PacketCodec()
    raw = body(32, [[8, 1, 0, 0, 1.0], [8, -1, 0, 0, 1.0], "junk", [9, 4, 0, [0], [1, 2]],
                    [32, []], [9, 2, 0, [5], [2.0]]])
    with pytest.raises(PartlyMalformed) as exc:
        codec.decode_body(raw)
    assert exc.value.bundle == Bundle([Value(1, 0, 0, 1.0), Batch(2, 0, [5], [2.0])])
    assert [(e.tag, e.channel) for e in exc.value.errors] == [
        (None, None), (None, None), (9, 4), (None, None)]  # -1 is no channel; [32, []] no int
    assert all("bundle part" in e.reason for e in exc.value.errors)
    assert not exc.value.fatal


@pytest.mark.parametrize("raw", [body(32, "not a list"), body(32), body(32, 5)])
def test_bundle_without_a_parts_array_is_malformed_as_a_whole(raw: bytes) -> None:
    from rlbridge.wire import RemoteProtocolError

    with pytest.raises(RemoteProtocolError) as exc:
        PacketCodec().decode_body(raw)
    assert not isinstance(exc.value, PartlyMalformed)


def test_partly_malformed_bundle_in_a_tcp_stream_keeps_the_stream() -> None:
    """The decoder hands it on as Malformed and goes on with the next frame."""
    from rlbridge.wire import FRAME_HEADER, MAGIC, PROTOCOL_VERSION, FrameDecoder, Malformed

    bad = body(32, [[8, 1, 0, 0, 1.0], "junk"])
    stream = (FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, len(bad)) + bad
              + PacketCodec().encode_frame(Value(2, 0, 0, 2.0)))
    decoder = FrameDecoder()
    first, second = decoder.feed(stream)
    assert isinstance(first, Malformed)
    assert isinstance(first.error, PartlyMalformed)
    assert first.error.bundle == Bundle([Value(1, 0, 0, 1.0)])
    assert second == Value(2, 0, 0, 2.0)
    assert decoder.buffered == 0


def test_client_flag_survives_the_header() -> None:
    data = PacketCodec().encode_datagram(Value(1, 0, 0, 1.0), TOKEN, FLAG_BUNDLES)
    assert peek_header(data) == (FLAG_BUNDLES, TOKEN)
    assert len(data) > DATAGRAM_HEADER.size


def test_a_failed_send_is_not_repeated_with_the_next_round() -> None:
    sent: list[bytes] = []

    def send(datagram: bytes) -> None:
        if not sent:
            sent.append(b"")  # the first datagram fails, as a full socket buffer would
            raise BlockingIOError
        sent.append(datagram)

    packer = DatagramPacker(PacketCodec(), TOKEN, 1400, send)
    packer.add(Value(1, 0, 0, 1.0))
    with pytest.raises(BlockingIOError):
        packer.flush()
    packer.add(Value(1, 1, 0, 2.0))
    packer.flush()
    assert [PacketCodec().decode_datagram(d)[2] for d in sent[1:]] == [Value(1, 1, 0, 2.0)]


@pytest.mark.parametrize("budget", [300, 1400, 9000])
def test_sealing_adds_its_overhead_to_each_datagram_and_changes_nothing_else(
        budget: int) -> None:
    """A sealed packer given SEAL_OVERHEAD more budget makes the plain packer's datagrams,
    byte for byte once opened: the same splits of a large batch, the same bundles. So at the
    same budget a sealed datagram holds what fits in 24 bytes less, not in a wider margin
    (more, smaller datagrams would each pay the cipher call and two system calls)."""
    stamps = [1_700_000_000_000_000_000 + i for i in range(4096)]
    rounds: list[list[Value | Batch]] = [
        [Value(c, 1, stamps[c], float(c)) for c in range(300)],
        [Batch(2, 0, stamps[:40], [1.5] * 40), Value(3, 9, 7, 2.5), Batch(4, 1, [8] * 3,
                                                                           [1, 2, 3])],
        [Batch(1, 5, stamps, [float(i) for i in range(4096)])],
    ]
    for packets in rounds:
        plain: list[bytes] = []
        sealed: list[bytes] = []
        a = DatagramPacker(PacketCodec(), TOKEN, budget, plain.append, flags=FLAG_BUNDLES)
        b = DatagramPacker(SealedCodec(KEY_A, KEY_B), TOKEN, budget + SEAL_OVERHEAD,
                           sealed.append, flags=FLAG_BUNDLES)
        for p in packets:
            assert a.add(p) == b.add(p) == 0
        a.flush()
        b.flush()
        receiver = SealedCodec(KEY_B, KEY_A)
        assert len(sealed) == len(plain)
        assert [len(d) for d in sealed] == [len(d) + SEAL_OVERHEAD for d in plain]
        assert max(len(d) for d in sealed) <= budget + SEAL_OVERHEAD
        assert ([receiver.decode_datagram(d)[2] for d in sealed]
                == [PacketCodec().decode_datagram(d)[2] for d in plain])
    assert len(sealed) > 73_000 // budget  # the last round: 4096 values split to fit
