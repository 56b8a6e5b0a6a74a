"""Periodic release at absolute deadlines, with lateness statistics.

Theory of operation
-------------------
Release ``k`` is due at ``t0 + k * period`` (``time.monotonic_ns``), computed from the
start, never by adding ``period`` to the previous wake-up and never by
``sleep(period)``: an error in one cycle does not carry over to the next, so there is
no drift. Each release records its lateness (wake-up time minus deadline) in a
preallocated ``array('q')`` ring of the last ``history`` cycles, so recording allocates
nothing; :meth:`PeriodicTimer.stats` sorts a copy on demand for p50/p99 and the maximum.

Overrun policy: if the body ran so long that the next deadline has passed, that release
happens at once (late). If even later deadlines have passed, those releases are skipped
and counted in ``missed``: the timer re-aligns to the grid instead of running a burst of
back-to-back cycles.

Waiting: with a stop :class:`threading.Event` the timer waits with ``Event.wait`` so
that ``stop()`` ends the wait at once; without one it uses ``time.sleep``, which CPython
3.11+ implements on Linux with ``clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)`` (the
relative timeout we pass is turned back into an absolute deadline within microseconds).
Python has no ``time.clock_nanosleep``. A wake-up before the deadline just waits again,
so lateness is never negative.

The GIL and wake-up lateness
----------------------------
A thread that wakes up must take the GIL back. If another thread is running Python code,
the waker asks for the GIL and the holder gives it up only at the next switch interval
(``sys.getswitchinterval()``, 5 ms by default): with a busy Python thread next to it,
lateness can reach 5 ms whatever the OS scheduler does. Threads blocked in I/O or C code
release the GIL and do not cause this. ``sys.setswitchinterval(0.0005)`` shortens the
worst case at some throughput cost; it is process-wide, so this module leaves it to the
owner of the loop (:class:`~rlbridge.hrt.coupling.ControlLoop` holds
:data:`~rlbridge.hrt.gil.HRT_SWITCH_INTERVAL` while it runs). ``spin`` (off by default)
wakes ``spin`` seconds early and busy-waits on the clock until the deadline; it trims OS
wake-up latency but holds the GIL while spinning, starving the I/O threads, so only use it
with a core to spare.
"""

from __future__ import annotations

import threading
import time
from array import array
from collections.abc import Callable
from dataclasses import dataclass

from rlbridge.csp.process import Process, ProcessLike, RunScope, as_process

Clock = Callable[[], int]
"""Returns monotonic time in nanoseconds."""

Waiter = Callable[[float, "threading.Event | None"], bool]
"""Waits up to ``seconds``; returns ``True`` if the stop event was set."""


def os_wait(seconds: float, stop: threading.Event | None) -> bool:
    """The default :data:`Waiter`: ``Event.wait`` when there is a stop event, else sleep."""
    if stop is None:
        time.sleep(seconds)
        return False
    return stop.wait(seconds)


@dataclass(frozen=True, slots=True)
class LatenessStats:
    """Release statistics; percentiles cover the last ``recorded`` cycles."""

    cycles: int
    missed: int
    recorded: int
    p50_ns: int
    p99_ns: int
    max_ns: int


class PeriodicTimer:
    """Releases a loop at ``t0 + k * period``; see the module docstring."""

    def __init__(
        self,
        period: float,
        *,
        history: int = 10_000,
        spin: float = 0.0,
        clock: Clock = time.monotonic_ns,
        wait: Waiter = os_wait,
    ) -> None:
        self._period = round(period * 1e9)
        if self._period <= 0:
            raise ValueError(f"period must be positive, got {period}")
        if history < 1:
            raise ValueError(f"history must be >= 1, got {history}")
        if spin < 0:
            raise ValueError(f"spin must be >= 0, got {spin}")
        self._spin = round(spin * 1e9)
        self._clock = clock
        self._wait = wait
        self._lateness = array("q", [0]) * history
        self._t0: int | None = None
        self._next = 1
        self._cycles = 0
        self._missed = 0
        self._max = 0

    @property
    def period_ns(self) -> int:
        """The period in nanoseconds."""
        return self._period

    def start(self) -> None:
        """Begin a new series: release ``k`` is due ``k`` periods from now."""
        self._begin()

    def _begin(self) -> int:
        t0 = self._t0 = self._clock()
        self._next = 1
        self._cycles = 0
        self._missed = 0
        self._max = 0
        return t0

    def deadline(self, k: int) -> int:
        """Absolute deadline (ns) of release ``k`` of the current series."""
        if self._t0 is None:
            raise RuntimeError("the timer has not been started")
        return self._t0 + k * self._period

    def wait_next(self, stop: threading.Event | None = None) -> bool:
        """Block until the next release; ``False`` if ``stop`` was set instead."""
        t0 = self._t0 if self._t0 is not None else self._begin()
        period = self._period
        clock = self._clock
        k = self._next
        deadline = t0 + k * period
        now = clock()
        if now >= deadline:
            latest = (now - t0) // period  # the newest deadline already passed
            if latest > k:
                self._missed += latest - k
                k = latest
                deadline = t0 + k * period
        else:
            coarse = deadline - self._spin
            while now < coarse:
                if self._wait((coarse - now) / 1e9, stop):
                    return False
                now = clock()
            while now < deadline:  # spin phase; empty unless spin > 0
                now = clock()
        if stop is not None and stop.is_set():
            return False
        late = now - deadline
        history = self._lateness
        history[self._cycles % len(history)] = late
        self._max = max(self._max, late)
        self._cycles += 1
        self._next = k + 1
        return True

    def stats(self) -> LatenessStats:
        """p50/p99 over the recorded window, maximum over the whole series."""
        recorded = min(self._cycles, len(self._lateness))
        if recorded == 0:
            return LatenessStats(self._cycles, self._missed, 0, 0, 0, 0)
        window = sorted(self._lateness[:recorded])
        return LatenessStats(
            cycles=self._cycles,
            missed=self._missed,
            recorded=recorded,
            p50_ns=window[_rank(50, recorded)],
            p99_ns=window[_rank(99, recorded)],
            max_ns=self._max,
        )

    def lateness(self) -> list[int]:
        """The recorded lateness samples in ns, oldest first (a copy)."""
        recorded = min(self._cycles, len(self._lateness))
        if self._cycles <= len(self._lateness):
            return list(self._lateness[:recorded])
        split = self._cycles % len(self._lateness)
        return list(self._lateness[split:]) + list(self._lateness[:split])


def _rank(percent: int, count: int) -> int:
    """Index of the nearest-rank percentile in a sorted list of ``count`` values."""
    return max(0, (percent * count + 99) // 100 - 1)


class Timed(Process):
    """Release ``proc`` at every tick of a periodic timer until stopped.

    The TERRA pattern of a recursion whose first step writes to a timer port: the body
    runs once per period, aligned to absolute deadlines. ``timer`` is a
    :class:`PeriodicTimer` or a period in seconds.
    """

    def __init__(
        self,
        proc: ProcessLike,
        timer: PeriodicTimer | float,
        *,
        name: str | None = None,
        hrt: bool = False,
    ) -> None:
        super().__init__(name=name, hrt=hrt)
        self.child = as_process(proc)
        self.timer = timer if isinstance(timer, PeriodicTimer) else PeriodicTimer(timer)

    def execute(self, scope: RunScope) -> None:
        inner = scope.marked(self.hrt)
        child = self.child
        timer = self.timer
        timer.start()
        while timer.wait_next(scope.stop):
            child.execute(inner)
