"""Idle strategies: how an SDK I/O thread waits for work (after Aeron's IdleStrategy family).

Theory of operation. The send thread waits for a written value (its doorbell), the receive
thread for a readable socket (``poll``), a blocking read of an incoming channel for a value
(its doorbell; it uses the receive thread's strategy). Parking in the kernel costs nothing
while idle but a wake-up costs tens of microseconds on a VM (futex or socket wake, then the
scheduler, then often the GIL); polling reacts within one poll but burns a core. The strategy
is a named object, chosen per thread (``Tuning(idle=...)``), that gets two functions
from the thread:

* ``poll()``: look once without waiting (the send thread's work predicate; ``poll`` with a
  zero timeout for the receive thread; the ring's length for a read); a truthy result is the
  work;
* ``block(timeout)``: wait in the kernel (doorbell or ``poll``), the park.

:class:`Park` only blocks (the default). :class:`SpinThenPark` polls for ``spin_us``,
then polls with ``os.sched_yield()`` between polls for ``yield_us``, then blocks: a value that
arrives within the spin window costs no wake-up, an idle thread sleeps after the window.
:class:`BusySpin` polls, with ``os.sched_yield()`` between polls, until its timeout, never
blocking.

**The GIL.** A Python thread that spins holds the GIL between polls; the control loop then
waits for it (up to ``sys.getswitchinterval()``, 5 ms by default) whenever it wants to run.
The receive thread's poll is a system call, which releases the GIL every time; the send
thread's poll is pure Python, so a spin phase without yields holds the GIL. That is why
:class:`BusySpin` yields between polls (without it, busy threads in publisher and subscriber
starved the control loop and, on 2 cores, the server: p50 540x the raw UDP pair's), and why a
spinning read yields in its poll (the value it waits for comes from a thread that needs the
GIL). docs/concepts.md has what each costs, measured: ``rlbridge bench latency --idle``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Protocol, TypeVar

T = TypeVar("T")

_now = time.perf_counter_ns


class IdleStrategy(Protocol):
    """Wait for work: ``poll`` looks without waiting, ``block`` parks (see module docstring)."""

    name: str

    def idle(self, poll: Callable[[], T], block: Callable[[float | None], T],
             timeout: float | None) -> T:
        """Return the first truthy ``poll()`` result, or ``block``'s, within ``timeout``."""
        ...


class Park:
    """Block in the kernel at once: no CPU while idle, a wake-up per value (the default)."""

    name = "park"

    def idle(self, poll: Callable[[], T], block: Callable[[float | None], T],
             timeout: float | None) -> T:
        """Block at once: the thread costs nothing until the kernel wakes it."""
        return block(timeout)

    def __repr__(self) -> str:
        return "Park()"


class SpinThenPark:
    """Poll for ``spin_us``, poll and yield the CPU (and GIL) for ``yield_us``, then park."""

    name = "spin"

    def __init__(self, spin_us: float = 20.0, yield_us: float = 200.0) -> None:
        if spin_us < 0 or yield_us < 0:
            raise ValueError(f"spin_us and yield_us must be >= 0, got {spin_us}, {yield_us}")
        self.spin_us = spin_us
        self.yield_us = yield_us
        self._spin_ns = int(spin_us * 1000)
        self._yield_ns = int(yield_us * 1000)

    def idle(self, poll: Callable[[], T], block: Callable[[float | None], T],
             timeout: float | None) -> T:
        """Spin, then poll with a yield between polls, then block for the time left."""
        got = poll()
        if got:
            return got
        start = _now()
        spin_end = start + self._spin_ns
        yield_end = spin_end + self._yield_ns
        deadline = None if timeout is None else start + int(timeout * 1e9)
        while True:
            now = _now()
            if deadline is not None and now >= deadline:
                return poll()
            if now >= yield_end:
                break
            if now >= spin_end:
                os.sched_yield()
            got = poll()
            if got:
                return got
        return block(None if deadline is None else max(0.0, (deadline - now) / 1e9))

    def __repr__(self) -> str:
        return f"SpinThenPark(spin_us={self.spin_us:g}, yield_us={self.yield_us:g})"


class BusySpin:
    """Poll until work or the timeout, never parking: the lowest latency, a whole core.

    Between polls it calls ``os.sched_yield()``, which lets the GIL go and hands the CPU to
    any other runnable thread: a Python thread that polled without it would keep the GIL
    from the control loop (its poll may be pure Python) and, with a busy thread in every
    process, starve the server of the machine's cores (measured: 540x the raw UDP pair's
    p50 before the yield). With nothing else runnable the yield returns at once.
    """

    name = "busy"

    def idle(self, poll: Callable[[], T], block: Callable[[float | None], T],
             timeout: float | None) -> T:
        """Poll, yield, poll, until work or the timeout; never calls ``block``."""
        deadline = None if timeout is None else _now() + int(timeout * 1e9)
        yield_cpu = os.sched_yield
        while True:
            got = poll()
            if got or (deadline is not None and _now() >= deadline):
                return got
            yield_cpu()

    def __repr__(self) -> str:
        return "BusySpin()"


PARK = Park()
#: Names ``Tuning(idle=...)`` and ``rlbridge bench latency --idle`` accept.
STRATEGIES: dict[str, Callable[[], IdleStrategy]] = {
    "park": Park, "spin": SpinThenPark, "busy": BusySpin}

IdleSpec = str | IdleStrategy


def idle_strategy(spec: IdleSpec) -> IdleStrategy:
    """A strategy from its name (``park``, ``spin``, ``busy``) or the object itself."""
    if isinstance(spec, str):
        make = STRATEGIES.get(spec)
        if make is None:
            raise ValueError(f"unknown idle strategy {spec!r}; choose one of "
                             f"{', '.join(STRATEGIES)} or pass an IdleStrategy object")
        return make()
    if not callable(getattr(spec, "idle", None)):
        raise TypeError(f"{spec!r} is not an idle strategy (it needs an idle() method)")
    return spec


def idle_pair(spec: IdleSpec | tuple[IdleSpec, IdleSpec]) -> tuple[IdleStrategy, IdleStrategy]:
    """``(send thread, receive thread)`` strategies: one spec for both, or a pair."""
    if isinstance(spec, tuple):
        if len(spec) != 2:
            raise ValueError("idle=(send, receive): give exactly two strategies")
        return idle_strategy(spec[0]), idle_strategy(spec[1])
    return idle_strategy(spec), idle_strategy(spec)
