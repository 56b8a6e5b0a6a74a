"""``IncomingChannel.deliver``'s inlined in-order path against the general path.

``deliver`` inlines the common case (a run that continues the sequence, one value or many,
no ``max_age_ms``, not ``latest``): the sequence tracker's bookkeeping and the ring write.
Any program of runs (in order, after a gap, duplicated, overlapping, longer than the ring)
interleaved with reads must end in the same state as a model built from the general path's
parts: ``SequenceTracker.accept_run`` for what is new, a bounded deque for the ring,
``InterarrivalJitter`` for the jitter. Every counter is compared, not only the values.
"""

from __future__ import annotations

import time
from collections import deque

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rlbridge.csp.bridge_channels import IncomingChannel
from rlbridge.errors import ChannelMisuseError
from rlbridge.wire.clock import InterarrivalJitter
from rlbridge.wire.sequence import SequenceTracker

F64 = "std_msgs/msg/Float64"

#: ``("run", first_seq, count)`` delivers values ``first_seq .. first_seq+count-1``;
#: ``("read", max_items)`` reads (``None``: everything).
Op = tuple[str, int | None, int]
programs = st.lists(
    st.one_of(
        st.tuples(st.just("run"), st.integers(0, 40), st.integers(0, 6)),
        st.tuples(st.just("read"), st.one_of(st.none(), st.integers(0, 4)), st.just(0)),
    ),
    max_size=40,
)


def _channel(capacity: int) -> IncomingChannel:
    return IncomingChannel(7, "/deliver", F64, None, transport="udp", blocking=True,
                           buffer_size=capacity)


@settings(max_examples=200, deadline=None)
@given(capacity=st.integers(1, 5), program=programs)
def test_any_program_of_runs_matches_the_general_path(capacity: int, program: list[Op]) -> None:
    ch = _channel(capacity)
    tracker = SequenceTracker()
    ring: deque[tuple[int, float]] = deque(maxlen=capacity)
    overwritten = delivered = arrived = 0
    last_stamp = 0
    stamp = 1_000  # stamps rise with every value sent: run order is not sequence order
    for op, arg, count in program:
        if op == "read":
            take = len(ring) if arg is None else min(arg, len(ring))
            expected = [ring.popleft()[1] for _ in range(take)]
            assert ch.read_many(arg) == expected
            continue
        assert arg is not None
        stamps = list(range(stamp, stamp + count))
        stamp += count
        values = [float(seq) for seq in range(arg, arg + count)]
        ch.deliver(arg, list(stamps), list(values))
        start = tracker.accept_run(arg, count)
        new = list(zip(stamps[start:], values[start:], strict=True))
        overwritten += max(0, len(ring) + len(new) - capacity)
        ring.extend(new)
        delivered += len(new)
        arrived += len(new)
        if new:
            last_stamp = new[-1][0]
    health = ch.health()
    stats = ch.statistics()
    assert (ch.lost, ch.duplicates) == (tracker.lost, tracker.duplicates + tracker.stale)
    assert ch._tracker.highest == tracker.highest
    assert ch._tracker.accepted == tracker.accepted
    assert health.values == delivered
    assert (stats.overwritten, stats.buffered) == (overwritten, len(ring))
    assert stats.written == delivered
    assert ch.last_stamp_ns == last_stamp
    assert ch.credit_limit() == arrived - len(ring) + capacity
    assert ch.read_many() == [v for _, v in ring]


def test_jitter_and_age_follow_the_newest_value_of_each_run() -> None:
    """The jitter estimate takes ``InterarrivalJitter.add`` with the run's newest stamp."""
    ch = _channel(8)
    reference = InterarrivalJitter()
    ages: list[int] = []
    for first, stamps in ((0, [100, 250]), (2, [400]), (3, [410, 900, 1_000])):
        ch.deliver(first, stamps, [0.0] * len(stamps))
        transit = ch._jitter.last_transit
        assert transit is not None
        reference.add(stamps[-1], stamps[-1] + transit)  # the same arrival time
        ages.append(transit)
        assert ch._jitter.jitter_ns == reference.jitter_ns
    one_way = ages[0]
    for age in ages[1:]:
        one_way += (age - one_way) // 16
    assert ch.health().one_way_ns == one_way
    assert ch.health().jitter_ns == reference.jitter_ns


@pytest.mark.parametrize("latest", [False, True])
def test_policies_still_apply_on_the_in_order_path(latest: bool) -> None:
    """``latest`` and ``max_age_ms`` leave the inlined path: their counters as before."""
    ch = IncomingChannel(7, "/deliver", F64, None, transport="udp", blocking=True,
                         buffer_size=8, latest=latest, max_age_ms=1_000)
    ch.deliver(0, [1, 2, 3], [1.0, 2.0, 3.0])  # stamps from 1970: all expired
    assert ch.expired == 3
    assert ch.read_many() == []
    now = time.time_ns()
    ch.deliver(3, [now, now, now], [4.0, 5.0, 6.0])
    assert ch.read_many() == ([6.0] if latest else [4.0, 5.0, 6.0])
    assert ch.health().overtaken == (2 if latest else 0)
    assert ch.health().values == (1 if latest else 3)


def test_a_second_writer_is_refused_and_the_channel_keeps_working() -> None:
    """The inlined ring write takes the writer's token like ``Channel.deliver_many``."""
    ch = _channel(4)
    token = ch._write_token
    token.pop()  # another writer is inside a write right now
    with pytest.raises(ChannelMisuseError):
        ch.deliver(0, [1], [1.0])
    token.append(None)
    ch.deliver(1, [2], [2.0])
    assert ch.read_many() == [2.0]


def test_a_closed_channel_takes_no_more_values() -> None:
    ch = _channel(4)
    ch.deliver(0, [1], [1.0])
    ch.close()
    ch.deliver(1, [2], [2.0])
    assert ch.read_many() == [1.0]
    assert ch.health().values == 1
