"""Tests of the periodic timer: absolute deadlines, overrun policy, statistics, stop."""

from __future__ import annotations

import threading

import pytest

from rlbridge.csp.process import Code, Sequential
from rlbridge.csp.timer import PeriodicTimer, Timed

MS = 1_000_000  # ns


class FakeClock:
    """Time as a parameter: waits advance the clock by the requested time plus ``oversleep``."""

    def __init__(self, oversleep: list[int] | None = None, tick: int = 0) -> None:
        self.now = 5_000 * MS
        self.oversleep = oversleep or [0]
        self.tick = tick  # added on every clock read (for the spin phase)
        self.waits: list[int] = []

    def __call__(self) -> int:
        self.now += self.tick
        return self.now

    def wait(self, seconds: float, stop: threading.Event | None) -> bool:
        requested = round(seconds * 1e9)
        self.waits.append(requested)
        self.now += requested + self.oversleep[(len(self.waits) - 1) % len(self.oversleep)]
        return stop is not None and stop.is_set()

    def work(self, ns: int) -> None:
        self.now += ns


def _timer(clock: FakeClock, period_ms: float = 1.0, **kwargs: object) -> PeriodicTimer:
    return PeriodicTimer(period_ms / 1000, clock=clock, wait=clock.wait, **kwargs)  # type: ignore[arg-type]


def test_releases_follow_absolute_deadlines_without_drift() -> None:
    clock = FakeClock(oversleep=[30_000])
    timer = _timer(clock)
    timer.start()
    t0 = clock.now
    work = [300_000, 700_000, 100_000, 950_000]
    for k in range(1, 1001):
        assert timer.wait_next()
        assert clock.now == t0 + k * MS + 30_000  # late by the oversleep only, every time
        clock.work(work[k % len(work)])
    stats = timer.stats()
    assert (stats.cycles, stats.missed) == (1000, 0)
    assert stats.p50_ns == stats.p99_ns == stats.max_ns == 30_000


def test_overrun_past_several_deadlines_skips_and_counts() -> None:
    clock = FakeClock()
    timer = _timer(clock)
    timer.start()
    t0 = clock.now
    assert timer.wait_next()
    clock.work(3 * MS + MS // 2)  # the body overran: now is t0 + 4.5 ms
    assert timer.wait_next()  # releases 2 and 3 are skipped; 4 happens at once, late
    assert clock.now == t0 + 4 * MS + MS // 2
    assert timer.wait_next()  # and the grid continues at 5 ms
    assert clock.now == t0 + 5 * MS
    stats = timer.stats()
    assert (stats.cycles, stats.missed, stats.max_ns) == (3, 2, MS // 2)


def test_short_overrun_releases_late_without_skipping() -> None:
    clock = FakeClock()
    timer = _timer(clock)
    timer.start()
    assert timer.wait_next()
    clock.work(MS + MS // 5)
    assert timer.wait_next()
    assert timer.stats().missed == 0
    assert timer.lateness() == [0, MS // 5]


def test_percentiles_and_history_window() -> None:
    clock = FakeClock(oversleep=list(range(0, 100_000, 1_000)))  # 0, 1 us, ... 99 us
    timer = _timer(clock, history=100)
    for _ in range(100):
        assert timer.wait_next()
    stats = timer.stats()
    assert (stats.recorded, stats.p50_ns, stats.p99_ns, stats.max_ns) == (
        100,
        49_000,
        98_000,
        99_000,
    )
    small = _timer(FakeClock(oversleep=[1, 2, 3, 4, 5, 6]), history=4)
    for _ in range(6):
        small.wait_next()
    assert small.lateness() == [3, 4, 5, 6]  # the last four, oldest first
    assert small.stats().max_ns == 6


def test_spin_wakes_early_and_busy_waits_to_the_deadline() -> None:
    clock = FakeClock(tick=10_000)
    timer = _timer(clock, spin=0.0002)
    timer.start()
    t0 = clock.now
    assert timer.wait_next()
    deadline = t0 + MS
    assert clock.waits[0] <= deadline - 200_000 - t0  # asked to wake 200 us early
    assert deadline <= clock.now < deadline + 10_000 + clock.tick  # then spun to it


def test_stop_event_ends_the_wait() -> None:
    clock = FakeClock()
    stop = threading.Event()
    timer = _timer(clock)
    assert timer.wait_next(stop)
    stop.set()
    assert not timer.wait_next(stop)
    assert timer.stats().cycles == 1


def test_timed_process_runs_the_body_once_per_release() -> None:
    clock = FakeClock(oversleep=[5_000])
    releases: list[int] = []

    def body() -> None:
        releases.append(clock.now)
        if len(releases) == 5:
            root.stop()

    root = Timed(Sequential(body), _timer(clock, period_ms=2.0))
    root.run()
    first = releases[0]
    assert [r - first for r in releases] == [0, 2 * MS, 4 * MS, 6 * MS, 8 * MS]
    assert root.timer.stats().cycles == 5


def test_real_clock_short_run() -> None:
    # Real sleeping: only structural facts are asserted, never how late a wake-up was.
    count = 0

    def body() -> None:
        nonlocal count
        count += 1
        if count == 20:
            root.stop()

    root = Timed(Code(body), 0.002)
    root.start()
    assert root.join(10.0)
    stats = root.timer.stats()
    assert stats.cycles == 20
    assert min(root.timer.lateness()) >= 0  # never released before its deadline
    assert stats.p50_ns <= stats.p99_ns <= stats.max_ns


def test_validation() -> None:
    with pytest.raises(ValueError, match="period"):
        PeriodicTimer(0)
    with pytest.raises(ValueError, match="history"):
        PeriodicTimer(0.001, history=0)
    with pytest.raises(ValueError, match="spin"):
        PeriodicTimer(0.001, spin=-1)
    with pytest.raises(RuntimeError, match="not been started"):
        PeriodicTimer(0.001).deadline(1)
