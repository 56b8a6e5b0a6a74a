"""The HRT loop and its helpers as one runnable unit: what every coupling pattern builds.

:class:`ControlLoop` is the hard-real-time process of thesis figure 5.7 (a bounded, timed
recursion); :class:`Coupling` composes it with the lower-priority helper processes a pattern
needs (:class:`Pump`: block on an input, forward; :class:`Ticker`: forward at a rate) and owns
the channels the pattern created. The recipes of chapter 5 are in :mod:`rlbridge.csp.patterns`.
"""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import Any, Final, TypedDict

from rlbridge.csp.bridge_channels import OutgoingChannel
from rlbridge.csp.channel import Channel
from rlbridge.csp.connection import ConnectionClosed
from rlbridge.csp.gil import HRT_SWITCH_INTERVAL, shorter_switch_interval
from rlbridge.csp.process import Code, Parallel, PriParallel, Process, RunScope
from rlbridge.csp.timer import LatenessStats, PeriodicTimer
from rlbridge.errors import ChannelClosed

__all__ = ["BaseCoupling", "ControlLoop", "Coupling", "LoopOptions", "Pump", "Ticker"]


class LoopOptions(TypedDict, total=False):
    """How a pattern's HRT loop runs; every recipe takes these as keyword arguments.

    ``period`` (s, default 1 ms), ``cycles`` (deadlines to run; ``None`` until stopped),
    ``priority`` (``PriParallel``, default; ``False``: plain threads), ``cpu`` (pin the loop),
    ``switch_interval`` (the GIL switch interval held while the loop runs, default
    :data:`~rlbridge.csp.gil.HRT_SWITCH_INTERVAL`; ``None`` leaves the interpreter's).
    """

    period: float
    cycles: int | None
    priority: bool
    cpu: int | None
    switch_interval: float | None


_SLEEP_WAIT_MAX_NS: Final = 20_000_000
"""Loops with a period up to this wait in ``time.sleep``; longer ones in ``Event.wait``."""


class ControlLoop(Process):
    """The HRT process of thesis figure 5.7: release ``body`` every ``period``, bounded.

    Releases follow a :class:`PeriodicTimer` (absolute deadlines; an overrun skips missed
    releases and counts them). With ``cycles`` the loop ends once that many deadlines have
    passed, so a loop that blocks (the naive receive) runs as long as one that does not and
    its skipped releases show up in ``stats().missed``. When the loop ends, for whatever
    reason, it sets the run's stop event (its sibling helpers wind down) and calls
    ``on_finish`` (the coupling closes its channels there, waking blocked helpers).
    """

    def __init__(
        self,
        body: Callable[[], object],
        *,
        period: float = 0.001,
        cycles: int | None = None,
        name: str = "hrt-loop",
        on_finish: Callable[[], None] | None = None,
        switch_interval: float | None = HRT_SWITCH_INTERVAL,
    ) -> None:
        super().__init__(name=name, hrt=True)
        self.switch_interval = switch_interval
        if cycles is not None and cycles < 1:
            raise ValueError(f"cycles must be >= 1, got {cycles}")
        self.cycles = cycles
        self.timer = PeriodicTimer(period, history=max(cycles or 0, 10_000))
        self._body = Code(body, name=name, hrt=True)
        self._on_finish = on_finish
        self.released = 0

    def execute(self, scope: RunScope) -> None:
        # The GIL switch interval is process-wide; the loop holds a short one while it runs.
        with shorter_switch_interval(self.switch_interval):
            self._release(self._body, scope.marked(True), scope.stop)

    def _release(self, body: Code, inner: RunScope, stop: threading.Event) -> None:
        timer = self.timer
        clock = time.monotonic_ns
        # Short periods wait in a plain sleep (clock_nanosleep) and look at the stop event
        # between releases: Event.wait runs threading.Condition's Python code on every
        # wake-up, about 10 us more at the median on the development VM, all of it with the
        # GIL. Long periods keep the event, so that stop() does not wait a whole period.
        wait_stop = stop if timer.period_ns > _SLEEP_WAIT_MAX_NS else None
        timer.start()
        end = None if self.cycles is None else timer.deadline(self.cycles)
        try:
            while timer.wait_next(wait_stop) and not stop.is_set():
                self.released += 1
                try:
                    body.execute(inner)
                except ChannelClosed:
                    if stop.is_set():  # closed by stop(): a blocked body was woken
                        return
                    raise
                if end is not None and clock() >= end:
                    return
        finally:
            stop.set()
            if self._on_finish is not None:
                self._on_finish()

    def stats(self) -> LatenessStats:
        """Lateness (actual release - deadline) over the releases so far."""
        return self.timer.stats()

    def lateness_ns(self) -> list[int]:
        """Per-release lateness in nanoseconds, oldest first (the absolute jitter)."""
        return self.timer.lateness()


class BaseCoupling(ABC):
    """What every coupling offers, whichever process its HRT loop runs in.

    ``run()`` executes in the calling thread; ``start()``/``stop()``/``join()`` run it in
    the background (an owner thread started by :attr:`process`). ``channels`` maps a role
    (``"in"``, ``"out"``, ``"handoff"``) to a channel the coupling created, so that tests
    and monitors can read its statistics; the coupling closes what ``closers`` close when
    the run ends, which wakes any helper blocked on them.
    """

    process: Process

    def __init__(self, name: str, *,
                 channels: dict[str, Channel[Any] | OutgoingChannel] | None = None,
                 closers: Sequence[Callable[[], None]] = ()) -> None:
        self.name = name
        self.channels: dict[str, Channel[Any] | OutgoingChannel] = dict(channels or {})
        self._closers = tuple(closers)
        self._closed = False
        self._close_lock = threading.Lock()

    def run(self) -> LatenessStats:
        """Run to the end in the calling thread; return the loop's lateness statistics."""
        try:
            self.process.run()
        finally:
            self.close_channels()
        return self.stats()

    def start(self) -> None:
        """Run in a background owner thread (pair with :meth:`stop` and :meth:`join`)."""
        self.process.start()

    def stop(self) -> None:
        """End the run early: set the stop event and close the owned channels."""
        self.process.stop()
        self.close_channels()

    def join(self, timeout: float | None = None) -> bool:
        """Wait for a started run; ``False`` on timeout; re-raises a process's error."""
        done = self.process.join(timeout)
        if done:
            self.close_channels()
        return done

    def close_channels(self) -> None:
        """Close what this coupling created (idempotent); wakes helpers blocked on them."""
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        for close in self._closers:
            close()

    @property
    @abstractmethod
    def released(self) -> int:
        """Releases of the HRT loop so far (it counts while it runs)."""

    @abstractmethod
    def stats(self) -> LatenessStats:
        """The loop's lateness statistics (so far, or of the finished run)."""

    @abstractmethod
    def lateness_ns(self) -> list[int]:
        """Per-release lateness in nanoseconds, oldest first (the absolute jitter)."""

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}>"


class Coupling(BaseCoupling):
    """An HRT loop thread, its helper threads and the channels they own; run it once.

    The in-process layout (``layout="thread"`` of the recipes): loop and helpers are threads
    of this interpreter. ``priority`` composes them in a :class:`PriParallel` (the loop
    highest), otherwise a :class:`Parallel`; ``cpu`` pins the loop's thread to that CPU
    (helpers stay free), so that a comparison with a reference loop pinned the same way
    measures the pattern, not where the scheduler happened to put the thread.
    """

    def __init__(
        self,
        name: str,
        body: Callable[[], object],
        *,
        helpers: Sequence[Process] = (),
        channels: dict[str, Channel[Any] | OutgoingChannel] | None = None,
        closers: Sequence[Callable[[], None]] = (),
        period: float = 0.001,
        cycles: int | None = None,
        priority: bool = True,
        cpu: int | None = None,
        switch_interval: float | None = HRT_SWITCH_INTERVAL,
    ) -> None:
        super().__init__(name, channels=channels, closers=closers)
        self.loop = ControlLoop(body, period=period, cycles=cycles, name=f"{name}:hrt",
                                on_finish=self.close_channels, switch_interval=switch_interval)
        self.helpers = tuple(helpers)
        composite = PriParallel if priority else Parallel
        cpus = None if cpu is None else [{cpu}, *([None] * len(self.helpers))]
        self.process = composite(self.loop, *self.helpers, name=name, cpus=cpus)

    @property
    def released(self) -> int:
        """Releases of the loop so far."""
        return self.loop.released

    def stats(self) -> LatenessStats:
        """The loop's lateness statistics so far."""
        return self.loop.stats()

    def lateness_ns(self) -> list[int]:
        """Per-release lateness in nanoseconds, oldest first."""
        return self.loop.lateness_ns()

    def __repr__(self) -> str:
        return f"<Coupling {self.name!r} helpers={len(self.helpers)}>"


class Pump(Process):
    """A lower-priority helper: call ``step`` until stopped or until its input closes.

    ``step`` blocks (a blocking channel read); :class:`ChannelClosed` or
    :class:`ConnectionClosed` ends the helper quietly: closing is how the coupling wakes it at
    the end, and a helper error would stop the HRT loop (nursery semantics), which a link that
    went away must not do. The loop keeps running on its latest values.
    """

    def __init__(self, step: Callable[[], object], *, name: str) -> None:
        super().__init__(name=name)
        self._step = Code(step, name=name)

    def execute(self, scope: RunScope) -> None:
        inner = scope.marked(self.hrt)
        step = self._step
        while not scope.stop.is_set():
            try:
                step.execute(inner)
            except (ChannelClosed, ConnectionClosed):
                return


class Ticker(Process):
    """A lower-priority timed helper: call ``step`` at ``rate_hz`` until stopped."""

    def __init__(self, step: Callable[[], object], rate_hz: float, *, name: str) -> None:
        super().__init__(name=name)
        if rate_hz <= 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        self._step = Code(step, name=name)
        self.timer = PeriodicTimer(1.0 / rate_hz, history=1)

    def execute(self, scope: RunScope) -> None:
        inner = scope.marked(self.hrt)
        timer = self.timer
        timer.start()
        while timer.wait_next(scope.stop):
            try:
                self._step.execute(inner)
            except (ChannelClosed, ConnectionClosed):
                return
