"""Pacing (credit and rate limit of an outgoing channel) and the stamped ring's partial
drain: pure bookkeeping, driven by a fake clock."""

from __future__ import annotations

import pytest

from rlbridge.client.channels.pacing import BURST_S, MIN_RATE_FRACTION, UNLIMITED, Pacing
from rlbridge.csp.stamped_ring import StampedRing

MS = 1_000_000


def test_no_limits_allow_everything() -> None:
    a = Pacing()
    assert a.allowance(0, 0) == UNLIMITED
    assert a.wait_s(0) is None


def test_credit_limits_by_sequence_number_and_never_goes_back() -> None:
    a = Pacing()
    assert a.on_credit(10)
    assert a.allowance(0, 0) == 10
    assert a.allowance(7, 0) == 3
    assert a.allowance(10, 0) == 0
    assert not a.on_credit(5)  # late or duplicated credit: ignored
    assert a.limit == 10
    assert a.wait_s(0) is None  # only credit can help: the send thread waits for it


def test_rate_refills_at_the_rate_up_to_the_burst() -> None:
    a = Pacing(1000.0, now_ns=0)
    burst = int(1000 * BURST_S)
    assert a.allowance(0, 0) == burst
    a.spend(burst)
    assert a.allowance(0, 0) == 0
    assert a.wait_s(0) == pytest.approx(0.001)
    assert a.allowance(0, 3 * MS) == 3
    assert a.allowance(0, 1000 * MS) == burst  # capped: a long pause is no licence to burst


def test_rate_and_credit_together_take_the_smaller() -> None:
    a = Pacing(1000.0, now_ns=0)
    a.on_credit(2)
    assert a.allowance(0, 0) == 2


def test_adaptive_rate_halves_on_loss_and_creeps_back() -> None:
    a = Pacing(1000.0, adapt=True)
    a.on_report(received=90, lost=10)
    assert a.rate_hz == 500
    a.on_report(received=1000, lost=5)  # under the tolerance: counts as no loss
    assert a.rate_hz == 500 * 1.05 + 1
    for _ in range(100):
        a.on_report(received=100, lost=0)
    assert a.rate_hz == 1000  # never above the maximum
    for _ in range(100):
        a.on_report(received=0, lost=100)
    assert a.rate_hz == 1000 * MIN_RATE_FRACTION  # never below the floor
    a.on_report(received=0, lost=0)  # an empty report changes nothing
    assert a.rate_hz == 1000 * MIN_RATE_FRACTION


def test_fixed_rate_ignores_reports_and_bad_settings_are_refused() -> None:
    a = Pacing(100.0)
    a.on_report(0, 100)
    assert a.rate_hz == 100
    with pytest.raises(ValueError, match="positive"):
        Pacing(0.0)
    with pytest.raises(ValueError, match="needs max_rate_hz"):
        Pacing(None, adapt=True)


def test_stamped_ring_partial_drain_keeps_the_rest_in_order() -> None:
    ring = StampedRing(8)
    for i in range(6):
        ring.push_stamped(100 + i, i)
    assert ring.drain_stamped(2) == ([100, 101], [0, 1])
    assert ring.drain_stamped(0) == ([], [])
    assert ring.drain_stamped() == ([102, 103, 104, 105], [2, 3, 4, 5])
    for i in range(12):  # overflow: the oldest four are overwritten, counted
        ring.push_stamped(i, i)
    assert ring.drain_stamped(3) == ([4, 5, 6], [4, 5, 6])
    assert ring.overwritten == 4
    assert ring.drain_stamped() == ([7, 8, 9, 10, 11], [7, 8, 9, 10, 11])
