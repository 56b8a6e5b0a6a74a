"""Clock-offset estimation and interarrival jitter, with fake clocks (no sleeping)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from rlbridge.wire.clock import ClockOffset, InterarrivalJitter, moving_average
from rlbridge.wire.link import LinkMonitor

MS = 1_000_000


def test_symmetric_path_gives_the_exact_offset() -> None:
    clock = ClockOffset()
    # Peer is 5 ms ahead; 2 ms each way; the peer holds the heartbeat 30 ms.
    t1 = 1_000 * MS
    t2 = t1 + 2 * MS + 5 * MS
    t3 = t2 + 30 * MS
    t4 = t3 - 5 * MS + 2 * MS
    sample = clock.add(t1, t2, t3, t4)
    assert sample is not None
    assert sample.delay_ns == 4 * MS
    assert clock.offset_ns == 5 * MS
    assert clock.error_bound_ns == 2 * MS


def test_asymmetric_path_error_stays_within_half_the_round_trip() -> None:
    clock = ClockOffset()
    offset = -7 * MS
    t1 = 50 * MS
    t2 = t1 + 9 * MS + offset  # 9 ms out, 1 ms back: the worst case for NTP
    t3 = t2 + 3 * MS
    t4 = t3 - offset + 1 * MS
    clock.add(t1, t2, t3, t4)
    assert abs(clock.offset_ns - offset) <= clock.error_bound_ns
    assert clock.error_bound_ns == 5 * MS


def test_minimum_delay_sample_wins_and_the_window_slides() -> None:
    clock = ClockOffset(window=3)
    offset = 3 * MS

    def exchange(start: int, out: int, back: int, bias: int = 0) -> None:
        t2 = start + out + offset + bias
        t3 = t2 + MS
        clock.add(start, t2, t3, t3 - offset - bias + back)

    exchange(0, 20 * MS, 1 * MS)  # queued on the way out: skewed, long
    exchange(100 * MS, 1 * MS, 1 * MS)  # clean
    exchange(200 * MS, 1 * MS, 15 * MS)  # queued on the way back
    assert clock.offset_ns == offset
    assert clock.error_bound_ns == MS
    # Three more long samples push the clean one out of the window.
    for k in range(3):
        exchange((300 + 100 * k) * MS, 6 * MS, 6 * MS)
    assert clock.error_bound_ns == 6 * MS
    assert clock.offset_ns == offset


def test_absurd_exchange_is_ignored() -> None:
    clock = ClockOffset()
    assert clock.add(100, 0, 500, 50) is None  # negative round trip (clock stepped)
    assert not clock.known
    assert clock.offset_ns == 0
    assert clock.error_bound_ns == -1
    with pytest.raises(ValueError, match="window"):
        ClockOffset(window=0)


def test_two_link_monitors_estimate_each_others_offset() -> None:
    """Client and server exchange heartbeats over a 3 ms / 5 ms path; server 40 ms ahead."""
    skew = 40 * MS
    up, down = 3 * MS, 5 * MS
    mono = 10_000 * MS
    wall = 1_700_000_000_000 * MS
    client = LinkMonitor(mono, 100 * MS)
    server = LinkMonitor(mono, 100 * MS)
    now = 0
    for _ in range(4):
        hb = client.make_heartbeat(mono + now, wall + now)
        now += up
        server.on_heartbeat(hb, mono + now, wall + now + skew)
        now += 7 * MS  # the server holds it a while
        hb = server.make_heartbeat(mono + now, wall + now + skew)
        now += down
        client.on_heartbeat(hb, mono + now, wall + now)
        now += 90 * MS
    est = client.stats(mono + now)
    assert est.clock_error_ns == (up + down) // 2
    assert abs(est.clock_offset_ns - skew) <= est.clock_error_ns
    assert est.clock_offset_ns == skew + (up - down) // 2
    srv = server.stats(mono + now)
    assert abs(srv.clock_offset_ns + skew) <= srv.clock_error_ns
    assert est.rtt_ns == up + down  # the monotonic echo still measures the round trip


def test_heartbeats_without_wall_clock_leave_the_estimate_alone() -> None:
    a = LinkMonitor(0, 100 * MS)
    b = LinkMonitor(0, 100 * MS)
    hb = a.make_heartbeat(1 * MS)
    assert (hb.wall_ns, hb.echo_wall_ns, hb.echo_rx_wall_ns) == (0, 0, 0)
    b.on_heartbeat(hb, 2 * MS, 123 * MS)
    a.on_heartbeat(b.make_heartbeat(3 * MS, 124 * MS), 4 * MS, 5 * MS)
    assert not a.clock.known
    assert not b.clock.known


def test_interarrival_jitter_follows_rfc3550() -> None:
    jitter = InterarrivalJitter()
    for i in range(200):  # perfectly regular: transit constant, jitter stays 0
        jitter.add(i * 10 * MS, i * 10 * MS + 2 * MS)
    assert jitter.jitter_ns == 0
    # Alternating 0 / 4 ms extra transit: |D| = 4 ms each time, J converges to 4 ms.
    for i in range(200, 600):
        jitter.add(i * 10 * MS, i * 10 * MS + 2 * MS + (4 * MS if i % 2 else 0))
    assert 3.9 * MS < jitter.jitter_ns <= 4 * MS


def test_moving_average_starts_at_the_first_sample_then_moves_a_sixteenth() -> None:
    assert moving_average(-1, 1_000) == 1_000
    assert moving_average(1_000, 2_600) == 1_100
    assert moving_average(1_000, 0) == 937  # floor division: rounds down, as the copies do


@pytest.mark.parity("rlbridge.wire.clock.InterarrivalJitter.add")
@given(st.lists(st.tuples(st.integers(0, 10**12), st.integers(-10**9, 10**9)), max_size=50))
def test_jitter_is_the_moving_average_of_transit_differences(
        values: list[tuple[int, int]]) -> None:
    """``add`` inlines ``moving_average``: the same estimate for any stamps and transits."""
    jitter = InterarrivalJitter()
    expected, last = 0, None
    for stamp, transit in values:
        jitter.add(stamp, stamp + transit)
        if last is not None:
            expected = moving_average(expected, abs(transit - last))
        last = transit
        assert jitter.jitter_ns == expected >= 0
