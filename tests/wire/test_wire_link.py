"""LinkMonitor with a fake clock: states, heartbeat schedule, RTT, next deadline. No sleeping."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rlbridge.wire import Heartbeat
from rlbridge.wire.link import LinkMonitor, LinkState

HB = 100_000_000  # 100 ms in ns
T0 = 5_000_000_000  # an arbitrary monotonic start


def test_constructor_checks_its_periods() -> None:
    with pytest.raises(ValueError, match="heartbeat period must be positive"):
        LinkMonitor(0, 0)
    with pytest.raises(ValueError, match="longer than one heartbeat period"):
        LinkMonitor(0, HB, HB)
    assert LinkMonitor(0, HB).timeout_ns == 3 * HB


def test_connected_degraded_lost_timing() -> None:
    link = LinkMonitor(T0, HB)
    assert link.state(T0) is LinkState.CONNECTED
    assert link.state(T0 + 3 * HB // 2 - 1) is LinkState.CONNECTED
    assert link.state(T0 + 3 * HB // 2) is LinkState.DEGRADED
    assert link.state(T0 + 3 * HB - 1) is LinkState.DEGRADED
    assert link.state(T0 + 3 * HB) is LinkState.LOST
    assert link.state(T0 + 100 * HB) is LinkState.LOST
    # Any packet from the peer brings it back.
    link.on_receive(T0 + 100 * HB)
    assert link.state(T0 + 100 * HB) is LinkState.CONNECTED
    assert link.stats(T0 + 101 * HB).silence_ns == HB


def test_custom_timeout() -> None:
    link = LinkMonitor(T0, HB, 10 * HB)
    assert link.state(T0 + 9 * HB) is LinkState.DEGRADED
    assert link.state(T0 + 10 * HB) is LinkState.LOST


def test_heartbeat_schedule() -> None:
    link = LinkMonitor(T0, HB)
    assert link.heartbeat_due(T0), "the first heartbeat goes out at once"
    hb = link.make_heartbeat(T0)
    assert hb == Heartbeat(sent_ns=T0, echo_ns=0)  # nothing heard yet: nothing to echo
    assert not link.heartbeat_due(T0 + HB - 1)
    assert link.heartbeat_due(T0 + HB)
    # A late heartbeat reschedules from when it was sent: no burst to catch up.
    link.make_heartbeat(T0 + 5 * HB)
    assert not link.heartbeat_due(T0 + 6 * HB - 1)
    assert link.heartbeat_due(T0 + 6 * HB)
    assert link.stats(T0).heartbeats_sent == 2


def test_echo_is_the_peer_stamp_aged_by_our_hold_time() -> None:
    link = LinkMonitor(T0, HB)
    link.make_heartbeat(T0)
    link.on_heartbeat(Heartbeat(sent_ns=777, echo_ns=0), T0 + 10)
    hb = link.make_heartbeat(T0 + 40)
    assert hb.sent_ns == T0 + 40
    assert hb.echo_ns == 777 + 30
    assert link.stats(T0).heartbeats_received == 1


def exchange(a: LinkMonitor, b: LinkMonitor, now: int, one_way: int, hold: int) -> int:
    """A sends, B holds the stamp ``hold`` ns and answers, A receives; returns A's clock."""
    hb_a = a.make_heartbeat(now)
    b.on_heartbeat(hb_a, now + one_way)
    hb_b = b.make_heartbeat(now + one_way + hold)
    a.on_heartbeat(hb_b, now + 2 * one_way + hold)
    return now + 2 * one_way + hold


def test_rtt_from_echo_excludes_the_peer_hold_time() -> None:
    a, b = LinkMonitor(T0, HB), LinkMonitor(T0, HB)
    assert a.stats(T0).rtt_ns == -1
    assert a.stats(T0).rtt_jitter_ns == -1
    now = exchange(a, b, T0, one_way=1_000_000, hold=37_000_000)
    assert a.stats(now).rtt_ns == 2_000_000
    assert a.stats(now).rtt_jitter_ns == 1_000_000
    # RFC 6298 smoothing: srtt += (sample - srtt) / 8, rttvar += (|srtt - sample| - rttvar) / 4
    now = exchange(a, b, now + HB, one_way=5_000_000, hold=1_000)
    sample = 10_000_000
    assert a.stats(now).rtt_jitter_ns == 1_000_000 + (abs(2_000_000 - sample) - 1_000_000) // 4
    assert a.stats(now).rtt_ns == 2_000_000 + (sample - 2_000_000) // 8


def test_no_rtt_sample_without_a_valid_echo() -> None:
    link = LinkMonitor(T0, HB)
    link.on_heartbeat(Heartbeat(sent_ns=1, echo_ns=0), T0 + 10)  # the peer heard nothing yet
    assert link.stats(T0 + 10).rtt_ns == -1
    link.on_heartbeat(Heartbeat(sent_ns=1, echo_ns=T0 + 99), T0 + 20)  # an echo from the future
    assert link.stats(T0 + 20).rtt_ns == -1
    assert link.stats(T0 + 20).heartbeats_received == 2


@settings(max_examples=300, deadline=None)
@given(heard=st.integers(0, 10 * HB), sent=st.integers(0, 10 * HB), now=st.integers(0, 12 * HB),
       timeout=st.integers(HB + 1, 5 * HB))
def test_next_deadline_is_the_earliest_change_not_yet_passed(heard: int, sent: int, now: int,
                                                              timeout: int) -> None:
    """The deadline is the earliest of the next heartbeat and the degraded and lost thresholds
    still ahead of ``now`` (never before ``now``), whatever the order of the three."""
    link = LinkMonitor(T0, HB, timeout)
    link.on_receive(T0 + heard)
    link.make_heartbeat(T0 + sent)
    at = T0 + now
    ahead = [t for t in (T0 + heard + 3 * HB // 2, T0 + heard + timeout) if t > at]
    assert link.next_deadline(at) == max(at, min([T0 + sent + HB, *ahead]))


def test_next_deadline_walkthrough() -> None:
    link = LinkMonitor(T0, HB)
    assert link.next_deadline(T0) == T0  # a heartbeat is due right away
    link.make_heartbeat(T0)
    assert link.next_deadline(T0) == T0 + HB  # the next heartbeat
    link.make_heartbeat(T0 + HB)
    assert link.next_deadline(T0 + HB) == T0 + 3 * HB // 2  # degraded comes first
    assert link.next_deadline(T0 + 3 * HB // 2) == T0 + 2 * HB  # already degraded: next heartbeat
    link.make_heartbeat(T0 + 2 * HB)
    assert link.next_deadline(T0 + 2 * HB) == T0 + 3 * HB  # lost and heartbeat at once
    link.make_heartbeat(T0 + 3 * HB)
    assert link.state(T0 + 3 * HB) is LinkState.LOST
    # Once lost, nothing changes until the next heartbeat: the deadline must not be "now",
    # or the I/O shim's timer would fire in a loop.
    assert link.next_deadline(T0 + 3 * HB) == T0 + 4 * HB
    assert link.next_deadline(T0 + 3 * HB + 1) == T0 + 4 * HB


# -- next_deadline as a property: nothing changes before it --------------------------------

events = st.lists(
    st.tuples(st.sampled_from(["wait", "receive", "heartbeat", "send"]),
              st.integers(0, 5 * HB)),
    max_size=30,
)


def observe(link: LinkMonitor, now: int) -> tuple[LinkState, bool]:
    return link.state(now), link.heartbeat_due(now)


@settings(deadline=None, max_examples=300)
@given(events, st.integers(2, 6))
def test_nothing_changes_before_next_deadline(script: list[tuple[str, int]], k: int) -> None:
    link = LinkMonitor(T0, HB, k * HB)
    now = T0
    for action, step in script:
        now += step
        if action == "receive":
            link.on_receive(now)
        elif action == "heartbeat":
            link.on_heartbeat(Heartbeat(sent_ns=now - 5, echo_ns=max(0, now - step)), now)
        elif action == "send" and link.heartbeat_due(now):
            link.make_heartbeat(now)
        deadline = link.next_deadline(now)
        assert deadline >= now
        seen = observe(link, now)
        if deadline == now:
            # Only a due heartbeat justifies an immediate deadline.
            assert link.heartbeat_due(now)
            continue
        for t in {now, now + (deadline - now) // 2, deadline - 1}:
            assert observe(link, t) == seen, f"changed at {t - T0} before deadline"
        assert observe(link, deadline) != seen, "nothing changed at the deadline"
