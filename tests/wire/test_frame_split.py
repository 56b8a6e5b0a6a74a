"""``encode_run_into``: a channel's run of values cut into TCP frames by count and by bytes.

Every frame it makes is read back by the receiver's own decoder with the same limit (which
ends the stream on a frame one byte over), so "fits" is the receiver's verdict, not ours.
"""

from __future__ import annotations

from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rlbridge.wire import Batch, Value
from rlbridge.wire.codec import FRAME_HEADER, FrameDecoder, PacketCodec, encode_run_into

CODEC = PacketCodec()


def split(values: list[Any], *, first_seq: int = 7, max_batch: int = 4096,
          limit: int = 1024) -> tuple[list[Value | Batch], list[tuple[int, int]], bytearray]:
    stamps = [1_000 + i for i in range(len(values))]
    buf = bytearray(b"before")  # frames are appended after what the round already holds
    refused: list[tuple[int, int]] = []
    frames = encode_run_into(CODEC, buf, 3, first_seq, stamps, values, max_batch, limit,
                             refused)
    assert buf[:6] == b"before"
    packets = FrameDecoder(CODEC, limit).feed(bytes(buf[6:]))  # raises on a frame over limit
    assert len(packets) == frames
    out: list[Value | Batch] = []
    for p in packets:
        assert isinstance(p, Value | Batch)
        out.append(p)
    return out, refused, buf


def unrolled(packets: list[Value | Batch]) -> list[tuple[int, int, Any]]:
    """(seq, stamp, value) of every value the frames carry, in frame order."""
    rows: list[tuple[int, int, Any]] = []
    for p in packets:
        if isinstance(p, Value):
            rows.append((p.seq, p.stamp_ns, p.value))
        else:
            rows.extend((p.first_seq + i, s, v)
                        for i, (s, v) in enumerate(zip(p.stamps, p.values, strict=True)))
    return rows


def value_body(seq: int, stamp: int, value: Any) -> int:
    return len(CODEC.encode_frame(Value(3, seq, stamp, value))) - FRAME_HEADER.size


sizes = st.lists(st.integers(0, 3000), max_size=60)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(sizes=sizes, max_batch=st.integers(1, 50), limit=st.integers(64, 4096))
def test_every_frame_fits_and_the_run_is_kept_in_order(sizes: list[int], max_batch: int,
                                                        limit: int) -> None:
    values: list[Any] = ["x" * n for n in sizes]
    packets, refused, _ = split(values, max_batch=max_batch, limit=limit)
    expected = [(7 + i, 1_000 + i, v) for i, v in enumerate(values)]
    # Left out: exactly the values whose own Value frame is over the limit, with that size.
    alone = {s: value_body(s, t, v) for s, t, v in expected}
    assert refused == [(s, alone[s]) for s, _, _ in expected if alone[s] > limit]
    gone = {s for s, _ in refused}
    # The rest: each value once, in order, with its own sequence number and stamp.
    assert unrolled(packets) == [row for row in expected if row[0] not in gone]
    for p in packets:
        assert isinstance(p, Value) or 2 <= len(p.values) <= max_batch


def test_small_values_take_one_batch_per_max_batch() -> None:
    """The common case is cut by count only, as before: one encoding per frame."""
    packets, refused, _ = split([float(i) for i in range(10)], max_batch=4, limit=1 << 20)
    assert [len(p.values) if isinstance(p, Batch) else 1 for p in packets] == [4, 4, 2]
    assert refused == []
    one, _, _ = split([1.5])
    assert one == [Value(3, 7, 1_000, 1.5)]


def test_a_burst_over_the_limit_is_cut_into_frames_that_fit() -> None:
    """The defect: 2,000 values of 1 KB made one frame over 1 MiB (the server ended the
    session); now every frame fits and all 2,000 values are in them."""
    values: list[Any] = [f"{i:04d}" + "v" * 1020 for i in range(2000)]
    packets, refused, buf = split(values, limit=1 << 20)
    assert len(buf) > 2_000_000
    assert len(packets) >= 2
    assert refused == []
    assert [v for _, _, v in unrolled(packets)] == values


def test_one_huge_value_among_small_ones_is_left_out_alone() -> None:
    values: list[Any] = ["a", "b", "z" * 5000, "c", "d"]
    packets, refused, _ = split(values, limit=1024)
    assert refused == [(9, value_body(9, 1_002, values[2]))]
    assert [(s, v) for s, _, v in unrolled(packets)] == [(7, "a"), (8, "b"), (10, "c"),
                                                         (11, "d")]
