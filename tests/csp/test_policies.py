"""Channel policies in the SDK's channels, without a network: latest, max age, redundancy,
health, the stamped outgoing ring and its single-writer guard."""

from __future__ import annotations

import threading
import time

import pytest

from benchmarks.redundancy import redundancy_cost
from rlbridge import Policy, SecondWriterError
from rlbridge.csp.bridge_channels import IncomingChannel, OutgoingChannel
from rlbridge.csp.channel import Doorbell
from rlbridge.csp.health import ChannelHealth
from rlbridge.csp.stamped_ring import StampedRing
from rlbridge.errors import ChannelMisuseError
from rlbridge.wire.link import LinkMonitor

MS = 1_000_000


def incoming(**kw: object) -> IncomingChannel:
    options: dict[str, object] = {"transport": "tcp", "blocking": False, "buffer_size": 8}
    options.update(kw)
    return IncomingChannel(1, "/sp", "std_msgs/msg/Float64", "data", **options)  # type: ignore[arg-type]


def outgoing(**kw: object) -> OutgoingChannel:
    options: dict[str, object] = {"transport": "tcp", "immediate": False, "buffer_size": 8,
                                  "doorbell": Doorbell()}
    options.update(kw)
    return OutgoingChannel(1, "/cmd", "std_msgs/msg/Float64", "data", **options)  # type: ignore[arg-type]


# -- incoming ------------------------------------------------------------------------------


def test_latest_delivers_only_the_newest_of_a_burst() -> None:
    ch = incoming(latest=True)
    now = time.time_ns()
    ch.deliver(0, [now - 30 * MS, now - 20 * MS, now - 10 * MS], [1.0, 2.0, 3.0])
    assert ch.read_many() == [3.0]
    h = ch.health()
    assert (h.overtaken, h.values, h.lost) == (2, 1, 0)


def test_without_latest_the_burst_is_delivered() -> None:
    ch = incoming()
    now = time.time_ns()
    ch.deliver(0, [now, now, now], [1.0, 2.0, 3.0])
    assert ch.read_many() == [1.0, 2.0, 3.0]
    assert ch.health().overtaken == 0


def test_max_age_drops_old_values_and_counts_them() -> None:
    ch = incoming(max_age_ms=50)
    now = time.time_ns()
    ch.deliver(0, [now - 500 * MS, now - 60 * MS, now - 1 * MS], [1.0, 2.0, 3.0])
    assert ch.read_many() == [3.0]
    ch.deliver(3, [now - 900 * MS], [4.0])  # all expired: nothing delivered
    assert ch.read_many() == []
    h = ch.health()
    assert (h.expired, h.values, h.lost) == (3, 1, 0)
    with pytest.raises(ValueError, match="max_age_ms"):
        incoming(max_age_ms=-1)


def test_read_with_age_pairs_each_value_with_its_own_stamp() -> None:
    ch = incoming(blocking=True)
    now = time.time_ns()
    ch.deliver(0, [now - 300 * MS, now - 100 * MS], ["old", "new"])
    # Each age is its own value's: at least since its stamp, at most until just after the
    # read (exact bounds from the clock, no allowance for a slow machine).
    value, age = ch.read_with_age()
    assert value == "old"
    assert 300 * MS <= age <= time.time_ns() - (now - 300 * MS)
    value, age = ch.read_with_age()
    assert value == "new"
    assert 100 * MS <= age <= time.time_ns() - (now - 100 * MS)
    assert ch.last_stamp_ns == now - 100 * MS


def test_local_writes_are_stamped_too() -> None:
    ch = incoming(blocking=True)
    ch.write(1.0)
    ch.deliver_many([2.0, 3.0])
    assert [ch.read_with_age()[0] for _ in range(3)] == [1.0, 2.0, 3.0]
    ch.write(4.0)
    assert ch.read_with_age().age_ns >= 0


def test_initial_value_has_no_age_and_reads_plainly() -> None:
    ch = incoming(initial=0.5)
    assert ch.read() == 0.5
    assert ch.read_with_age() == (0.5, -1)
    assert ch.try_read() == 0.5
    assert ch.age_ns == -1


def test_ages_are_corrected_by_the_measured_clock_offset() -> None:
    """A server 2 s ahead: its stamps look 2 s in the future without the correction."""
    link = LinkMonitor(0, 100 * MS)
    skew = 2_000 * MS
    wall = time.time_ns()
    # One exchange, 1 ms each way, so the error bound is 1 ms.
    hb = link.make_heartbeat(1, wall)
    peer = LinkMonitor(0, 100 * MS)
    peer.on_heartbeat(hb, 2, wall + MS + skew)
    link.on_heartbeat(peer.make_heartbeat(3, wall + MS + skew), 4, wall + 2 * MS)
    assert link.clock.offset_ns == skew
    ch = incoming(link=link, max_age_ms=100)
    server_now = time.time_ns() + skew
    ch.deliver(0, [server_now - 10 * MS], [1.0])
    value, age = ch.read_with_age()
    assert value == 1.0
    assert 10 * MS <= age <= time.time_ns() + skew - (server_now - 10 * MS)  # offset applied
    assert ch.health().clock_error_ns == MS
    assert ch.health().expired == 0


def test_duplicates_and_gaps_show_in_health() -> None:
    ch = incoming()
    now = time.time_ns()
    ch.deliver(0, [now, now], [1.0, 2.0])
    ch.deliver(1, [now, now], [2.0, 3.0])  # redundant copy of 1, new 2
    ch.deliver(5, [now], [6.0])  # 3 and 4 lost
    h = ch.health()
    assert isinstance(h, ChannelHealth)
    assert (h.duplicates, h.lost, h.values) == (1, 2, 4)
    assert h.jitter_ns >= 0
    assert h.one_way_ns >= 0


# -- outgoing ------------------------------------------------------------------------------


def test_outgoing_ring_keeps_each_stamp_with_its_value() -> None:
    ch = outgoing(buffer_size=4)
    for v in range(10):
        ch.write(float(v))
    first, stamps, values, repeated = ch.take()
    assert values == [6.0, 7.0, 8.0, 9.0]
    assert stamps == sorted(stamps)
    assert (first, repeated) == (0, 0)
    assert ch.statistics().overwritten == 6
    assert ch.health().overwritten == 6


def test_stamped_ring_batch_and_wraparound() -> None:
    ring = StampedRing(3)
    ring.push_stamped(1, "a")
    ring.push_many_stamped(2, ["b", "c", "d", "e"])  # longer than the free space
    assert ring.drain_stamped() == ([2, 2, 2], ["c", "d", "e"])
    ring.push_stamped(3, "f")
    ring.push_stamped(4, "g")
    assert ring.drain_stamped() == ([3, 4], ["f", "g"])
    assert ring.drain_stamped() == ([], [])
    assert ring.overwritten == 2


def test_latest_outgoing_sends_newest_and_holds_while_congested() -> None:
    ch = outgoing(latest=True)
    for v in (1.0, 2.0, 3.0):
        ch.write(v)
    assert ch.take(congested=True)[2] == []  # held back
    assert ch.holding
    ch.write(4.0)
    assert ch.take(congested=True)[2] == []  # 4 replaces the held 3
    first, _stamps, values, _ = ch.take(congested=False)
    assert (first, values) == (0, [4.0])
    assert not ch.holding
    ch.write(5.0)
    first, _stamps, values, _ = ch.take()
    assert (first, values) == (1, [5.0])  # no sequence gap for the overtaken ones
    assert ch.health().overtaken == 3
    ch.write(6.0)
    ch.take(congested=True)
    ch.close()  # the held value never left: counted, not silently lost
    assert ch.statistics().dropped == 1


def test_redundant_udp_take_repeats_previous_values() -> None:
    ch = outgoing(transport="udp", redundancy=2)
    sent = []
    for v in range(5):
        ch.write(float(v))
        sent.append(ch.take())
    assert sent[0][0::2] == (0, [0.0])
    assert sent[1] == (0, sent[1][1], [0.0, 1.0], 1)
    assert sent[4] == (2, sent[4][1], [2.0, 3.0, 4.0], 2)
    tcp = outgoing(transport="tcp", redundancy=2)  # TCP loses nothing: redundancy ignored
    tcp.write(1.0)
    tcp.write(2.0)
    tcp.take()
    tcp.write(3.0)
    assert tcp.take()[2] == [3.0]
    with pytest.raises(ValueError, match="redundancy=17"):  # checked where the policy is made
        Policy(redundancy=17)


def test_outgoing_max_age_drops_values_that_waited_too_long() -> None:
    ch = outgoing(max_age_ms=1)
    ch.write(1.0)
    time.sleep(0.01)  # the value must age beyond 1 ms; no timing is asserted
    ch.write(2.0)
    assert ch.take()[2] == [2.0]
    assert ch.health().expired == 1


def test_second_writer_thread_is_refused_while_the_first_lives() -> None:
    ch = outgoing()
    ch.write(1.0)
    errors: list[BaseException] = []

    def intruder() -> None:
        try:
            ch.write(2.0)
        except ChannelMisuseError as exc:
            errors.append(exc)

    t = threading.Thread(target=intruder)
    t.start()
    t.join()
    assert len(errors) == 1
    assert isinstance(errors[0], SecondWriterError)
    assert "single producer" in str(errors[0])
    assert ch.take()[2] == [1.0]


def test_writer_end_passes_on_when_the_first_thread_ended() -> None:
    ch = outgoing()
    t = threading.Thread(target=ch.write, args=(1.0,))
    t.start()
    t.join()
    ch.write(2.0)  # the first writer is gone: this thread takes over
    errors: list[BaseException] = []

    def other() -> None:
        try:
            ch.write_many([3.0])
        except SecondWriterError as exc:
            errors.append(exc)

    t2 = threading.Thread(target=other)
    t2.start()
    t2.join()
    assert len(errors) == 1  # this thread lives, so the other is refused
    assert ch.take()[2] == [1.0, 2.0]


def test_redundancy_cost_grows_by_one_stamped_value_per_k() -> None:
    rows = redundancy_cost(ks=(0, 1, 2, 3), warmup=10)
    assert [r.k for r in rows] == [0, 1, 2, 3]
    sizes = [r.payload_bytes for r in rows]
    step = sizes[2] - sizes[1]
    assert sizes[3] - sizes[2] == step  # each repeated value costs the same
    assert 9 < step <= 20  # a float64 and an int64 stamp, msgpack-encoded
    assert rows[0].ratio == 1.0
    assert rows[3].residual_loss_at_1pct == pytest.approx(1e-8)
