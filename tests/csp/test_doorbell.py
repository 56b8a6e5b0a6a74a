"""The doorbell's gates, and how a blocking read waits by its idle strategy (mechanisms only)."""

from __future__ import annotations

import threading

import pytest

from rlbridge.csp.channel import Channel
from rlbridge.csp.doorbell import Doorbell
from rlbridge.csp.idle import BusySpin, SpinThenPark
from waiting import wait_until

JOIN = 10.0  # generous bound for joins and waits; only reached when a test fails


class CountingBell(Doorbell):
    __slots__ = ("rings",)

    def __init__(self) -> None:
        super().__init__()
        self.rings = 0

    def ring(self) -> None:
        self.rings += 1
        super().ring()


def test_a_ring_wakes_every_blocked_waiter_and_leaves_no_gate() -> None:
    bell = Doorbell()
    state = {"go": False}
    woke: list[bool] = []
    threads = [threading.Thread(target=lambda: woke.append(
        bell.wait_for(lambda: state["go"], JOIN))) for _ in range(3)]
    for t in threads:
        t.start()
    wait_until(lambda: bell.waiting == 3 and len(bell._gates) == 3, "all three are parked")
    state["go"] = True
    bell.ring()
    for t in threads:
        t.join(JOIN)
    assert woke == [True, True, True]
    assert bell.waiting == 0
    assert bell._gates == []


def test_a_ring_with_nobody_waiting_releases_nothing() -> None:
    bell = Doorbell()
    bell.ring()
    assert bell._gates == []
    assert bell.wait_for(lambda: True) is True  # the earlier ring left nothing behind
    assert bell.waiting == 0


def test_a_timed_out_wait_takes_its_gate_off_the_list() -> None:
    bell = Doorbell()
    assert bell.wait_for(lambda: False, 0.01) is False
    assert bell._gates == []
    assert bell.waiting == 0


def test_a_ring_that_finds_the_predicate_false_parks_the_waiter_again() -> None:
    bell = Doorbell()
    state = {"go": False}
    got: list[bool] = []
    t = threading.Thread(target=lambda: got.append(bell.wait_for(lambda: state["go"], JOIN)))
    t.start()
    wait_until(lambda: len(bell._gates) == 1, "the waiter is parked")
    bell.ring()  # spurious: nothing changed
    wait_until(lambda: len(bell._gates) == 1, "the waiter is parked again")
    assert t.is_alive()
    state["go"] = True
    bell.ring()
    t.join(JOIN)
    assert got == [True]


@pytest.mark.parametrize("idle", [None, SpinThenPark(spin_us=0, yield_us=0)],
                         ids=["parked", "spun-then-parked"])
def test_a_parked_reader_is_woken_by_a_write_with_one_ring(idle: SpinThenPark | None) -> None:
    """A reader that parks (at once, or after its spin window) is woken by the write's ring."""
    bell = CountingBell()
    chan: Channel[int] = Channel(4, doorbell=bell)
    if idle is not None:
        chan.read_idle = idle
    got: list[int] = []
    t = threading.Thread(target=lambda: got.append(chan.read(timeout=JOIN)))
    t.start()
    wait_until(lambda: len(bell._gates) == 1, "the reader is parked")
    chan.write(7)
    t.join(JOIN)
    assert got == [7]
    assert bell.rings == 1


@pytest.mark.parametrize("idle", [BusySpin(), SpinThenPark(spin_us=1e7, yield_us=0)])
def test_a_spinning_reader_takes_the_value_without_a_ring(
        idle: BusySpin | SpinThenPark, monkeypatch: pytest.MonkeyPatch) -> None:
    bell = CountingBell()
    chan: Channel[int] = Channel(4, doorbell=bell)
    chan.read_idle = idle
    got: list[int] = []
    t = threading.Thread(target=lambda: got.append(chan.read(timeout=JOIN)))
    t.start()
    wait_until(lambda: chan.statistics().waiting_readers == 1, "the reader polls")
    chan.write(7)
    t.join(JOIN)
    assert got == [7]
    assert bell.rings == 0  # it polled, never parked: the write had nobody to wake
    assert bell.waiting == 0


def test_a_spinning_read_times_out() -> None:
    chan: Channel[int] = Channel(4)
    chan.read_idle = BusySpin()
    with pytest.raises(TimeoutError):
        chan.read(timeout=0.01)
