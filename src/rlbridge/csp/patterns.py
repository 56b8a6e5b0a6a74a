"""Coupling patterns between a hard-real-time loop and the bridge (thesis chapter 5).

Each function returns a :class:`Coupling`: an HRT :class:`ControlLoop` (a timed, bounded
recursion marked ``hrt``), the lower-priority helper processes the pattern needs, and the
channels it created, composed as ``PriParallel(loop, *helpers)`` so that the loop gets the
highest priority the OS grants. The control law is a plain callable; the recipe does the
plumbing.

============================  ======  ========================================================
function                      thesis  what the HRT loop touches each cycle
============================  ======  ========================================================
:func:`reference`             5.7     nothing (the baseline every pattern is compared with)
:func:`receive_nonblocking`   5.3     a non-blocking incoming bridge channel (latest value)
:func:`receive_blocking`      5.4     a non-blocking local channel fed by a lower-priority
                                      process that does the *blocking* bridge read
:func:`receive_naive`         5.3.1   a blocking incoming bridge channel: the loop waits for
                                      the network (``RealTimeWarning``, ``hrt_blocking_reads``)
:func:`send_buffered`         5.5     a blocking buffered local channel; a lower-priority
                                      process sends every value and calls ``bridge.send()``
:func:`send_sampled`          5.6     a non-blocking local channel of size 1; a lower-priority
                                      timed process forwards the latest value at a lower rate
:func:`send_loop`             5.10    a ``through_buffer`` bridge channel sent by the SDK's
                                      send loop (``Bridge.connect(send_rate_hz=...)``)
:func:`send_naive`            5.2.2   an immediate bridge channel (``through_buffer=False``):
                                      a write may wake the send thread (one futex call)
============================  ======  ========================================================

Why the proper patterns keep the loop's timing: every operation the loop does is a ring
buffer operation (no lock, no system call), except ringing a doorbell when a consumer sleeps
(``send_buffered``, ``send_naive``). Whatever waits (for the network, for a value) waits in a
lower-priority thread. In CPython the loop still shares the GIL with those threads and with the
SDK's receive and send threads: see ``docs/gil.md`` for what that costs. ``Bridge.connect``
shortens the GIL switch interval to :data:`DEFAULT_SWITCH_INTERVAL` (0.5 ms) for that reason;
:func:`realtime_switch_interval` does the same for a process without a bridge.

Lifetimes: a coupling owns the channels it created. When the loop has run its ``cycles`` (or
:meth:`Coupling.stop` is called) the run's stop event is set, its incoming bridge channels are
unsubscribed and its local channels closed, which wakes any helper blocked on them; then
``run()`` returns. Outgoing bridge channels stay bound until ``bridge.close()``, which flushes
them, so the last values written by the loop are not lost. A coupling runs once.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, Final

from rlbridge.csp.bridge import DEFAULT_SWITCH_INTERVAL, Bridge, Transport
from rlbridge.csp.bridge_channels import IncomingChannel, OutgoingChannel
from rlbridge.csp.channel import Channel
from rlbridge.csp.connection import ConnectionClosed
from rlbridge.csp.errors import ChannelClosed, NoValueYet
from rlbridge.csp.process import Code, Parallel, PriParallel, Process, RunScope
from rlbridge.csp.timer import LatenessStats, PeriodicTimer

__all__ = [
    "DEFAULT_SWITCH_INTERVAL",
    "ControlLoop",
    "Coupling",
    "realtime_switch_interval",
    "receive_blocking",
    "receive_naive",
    "receive_nonblocking",
    "reference",
    "send_buffered",
    "send_loop",
    "send_naive",
    "send_sampled",
]

ReceiveLaw = Callable[[Any], object]
"""Control law of a receive pattern: called once per cycle with the value read."""

SendLaw = Callable[[], Any]
"""Control law of a send pattern: called once per cycle, returns the value to send."""



def realtime_switch_interval(seconds: float = DEFAULT_SWITCH_INTERVAL) -> float:
    """Shorten CPython's GIL switch interval for a process that runs an HRT loop.

    A loop thread that wakes while another thread runs Python code waits for the GIL until
    that thread reaches a blocking call, or at most one switch interval (5 ms by default)
    before it forces a hand-over. Shorter means a busy Python thread (a user's SRT process,
    a helper) can delay the loop by at most ``seconds``; the cost is more GIL hand-overs
    between CPU-bound threads. It is process-wide: ``Bridge.connect`` applies the default
    (unless given ``switch_interval=None``); call this in a loop process without a bridge, or
    to choose another value. Returns the previous value.
    """
    if seconds <= 0:
        raise ValueError(f"switch interval must be positive, got {seconds}")
    previous = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    return previous


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
    ) -> None:
        super().__init__(name=name, hrt=True)
        if cycles is not None and cycles < 1:
            raise ValueError(f"cycles must be >= 1, got {cycles}")
        self.cycles = cycles
        self.timer = PeriodicTimer(period, history=max(cycles or 0, 10_000))
        self._body = Code(body, name=name, hrt=True)
        self._on_finish = on_finish
        self.released = 0

    def execute(self, scope: RunScope) -> None:
        inner = scope.marked(True)
        stop = scope.stop
        timer = self.timer
        body = self._body
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


class Coupling:
    """An HRT loop, its helper processes and the channels they own; run it once.

    ``run()`` executes in the calling thread; ``start()``/``stop()``/``join()`` run it in
    the background. ``channels`` maps a role (``"in"``, ``"out"``, ``"handoff"``) to the
    channel, so that tests and monitors can read its statistics.
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
    ) -> None:
        self.name = name
        self.channels: dict[str, Channel[Any] | OutgoingChannel] = dict(channels or {})
        self._closers = tuple(closers)
        self._closed = False
        self._close_lock = threading.Lock()
        self.loop = ControlLoop(body, period=period, cycles=cycles, name=f"{name}:hrt",
                                on_finish=self.close_channels)
        self.helpers = tuple(helpers)
        composite = PriParallel if priority else Parallel
        self.process: Process = composite(self.loop, *self.helpers, name=name)

    def run(self) -> LatenessStats:
        """Run to the end in the calling thread; return the loop's lateness statistics."""
        try:
            self.process.run()
        finally:
            self.close_channels()
        return self.loop.stats()

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

    def stats(self) -> LatenessStats:
        """The loop's lateness statistics so far."""
        return self.loop.stats()

    def __repr__(self) -> str:
        return f"<Coupling {self.name!r} helpers={len(self.helpers)}>"


class _Pump(Process):
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


class _Ticker(Process):
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


def _unsubscriber(bridge: Bridge, channel: IncomingChannel) -> Callable[[], None]:
    """Close an incoming channel (waking a blocked reader) and unbind it on the server."""

    def close() -> None:
        channel.close()  # first: it must happen even when the link is already gone
        with contextlib.suppress(ConnectionClosed, OSError):
            bridge.unsubscribe(channel)

    return close


# -- the baseline ------------------------------------------------------------------------------


def reference(
    control: Callable[[], object],
    *,
    period: float = 0.001,
    cycles: int | None = None,
    priority: bool = True,
) -> Coupling:
    """The loop alone (thesis figure 5.7): the baseline for every pattern, no bridge."""
    return Coupling("reference", control, period=period, cycles=cycles, priority=priority)


# -- receive patterns --------------------------------------------------------------------------


def receive_nonblocking(
    bridge: Bridge,
    topic: str,
    msg_type: str,
    control: ReceiveLaw,
    *,
    field: str | None = "data",
    transport: Transport = "udp",
    initial: Any = 0.0,
    period: float = 0.001,
    cycles: int | None = None,
    priority: bool = True,
) -> Coupling:
    """Figure 5.3: the loop reads a non-blocking bridge channel of size 1 every cycle.

    The read is a ring operation; with nothing new it returns the latest value again (or
    ``initial``), so the loop never waits for the network. ``channels["in"]`` is the
    :class:`IncomingChannel` (``age_ns``, ``lost``, ``statistics()``).
    """
    incoming = bridge.subscribe(topic, msg_type, field, transport=transport, blocking=False,
                                buffer_size=1, initial=initial)

    def body() -> None:
        control(incoming.read())

    return Coupling("receive-nonblocking", body, channels={"in": incoming},
                    closers=[_unsubscriber(bridge, incoming)], period=period, cycles=cycles,
                    priority=priority)


def receive_blocking(
    bridge: Bridge,
    topic: str,
    msg_type: str,
    control: ReceiveLaw,
    *,
    field: str | None = "data",
    transport: Transport = "udp",
    buffer_size: int = 16,
    process: Callable[[Any], Any] | None = None,
    initial: Any = 0.0,
    period: float = 0.001,
    cycles: int | None = None,
    priority: bool = True,
) -> Coupling:
    """Figure 5.4: a lower-priority process does the blocking read, the loop never waits.

    The helper reads every value from a blocking bridge channel (``buffer_size`` values of
    slack), applies ``process`` (a sanity check, a sequence controller; ``None`` = identity)
    and writes the result to a non-blocking local channel of size 1, which the loop reads.
    The helper's timing follows the message rate; the loop's follows its timer.
    ``channels``: ``"in"`` (bridge, blocking) and ``"handoff"`` (local, non-blocking).
    """
    incoming = bridge.subscribe(topic, msg_type, field, transport=transport, blocking=True,
                                buffer_size=buffer_size)
    handoff: Channel[Any] = Channel(1, blocking=False, initial=initial,
                                    name=f"{topic} handoff")

    def forward() -> None:
        value = incoming.read()
        handoff.write(value if process is None else process(value))

    def body() -> None:
        control(handoff.read())

    return Coupling("receive-blocking", body,
                    helpers=[_Pump(forward, name="receive-blocking:srt")],
                    channels={"in": incoming, "handoff": handoff},
                    closers=[_unsubscriber(bridge, incoming), handoff.close],
                    period=period, cycles=cycles, priority=priority)


def receive_naive(
    bridge: Bridge,
    topic: str,
    msg_type: str,
    control: ReceiveLaw,
    *,
    field: str | None = "data",
    transport: Transport = "udp",
    period: float = 0.001,
    cycles: int | None = None,
    priority: bool = True,
) -> Coupling:
    """For comparison only: the loop reads a *blocking* bridge channel directly.

    The loop then runs when messages arrive, not when its timer says (thesis 5.3.1: jitter
    up to one period, releases skipped). The channel reports it: a ``RealTimeWarning`` the
    first time and ``statistics().hrt_blocking_reads`` every time.
    """
    incoming = bridge.subscribe(topic, msg_type, field, transport=transport, blocking=True,
                                buffer_size=1)

    def body() -> None:
        control(incoming.read())

    return Coupling("receive-naive", body, channels={"in": incoming},
                    closers=[_unsubscriber(bridge, incoming)], period=period, cycles=cycles,
                    priority=priority)


# -- send patterns -----------------------------------------------------------------------------


def send_naive(
    bridge: Bridge,
    topic: str,
    msg_type: str,
    control: SendLaw,
    *,
    field: str | None = "data",
    transport: Transport = "udp",
    period: float = 0.001,
    cycles: int | None = None,
    priority: bool = True,
) -> Coupling:
    """For comparison: the loop writes an immediate bridge channel (``through_buffer=False``).

    No socket call happens in the loop (the SDK's send thread does it), but a write wakes that
    thread when it sleeps, which is a system call in the loop and a GIL competitor right after.
    """
    out = bridge.publish(topic, msg_type, field, transport=transport, through_buffer=False)

    def body() -> None:
        out.write(control())

    return Coupling("send-naive", body, channels={"out": out}, period=period, cycles=cycles,
                    priority=priority)


def send_buffered(
    bridge: Bridge,
    topic: str,
    msg_type: str,
    control: SendLaw,
    *,
    field: str | None = "data",
    transport: Transport = "udp",
    buffer_size: int = 64,
    period: float = 0.001,
    cycles: int | None = None,
    priority: bool = True,
) -> Coupling:
    """Figure 5.5: send every value, in order, through a lower-priority process.

    The loop writes a blocking buffered local channel (never blocks; overwrites and counts
    when ``buffer_size`` values pile up); the helper blocks reading it, moves everything it
    finds into a ``through_buffer`` bridge channel and calls ``bridge.send()``. At the end
    the helper drains the handoff before it stops, so no value written by the loop is lost.
    ``channels``: ``"handoff"`` (local) and ``"out"`` (bridge).
    """
    out = bridge.publish(topic, msg_type, field, transport=transport, through_buffer=True,
                         buffer_size=max(buffer_size, 1024))
    handoff: Channel[Any] = Channel(buffer_size, blocking=True, name=f"{topic} handoff")

    def forward() -> None:
        try:
            first = handoff.read()  # buffered values come first, even after close
        except ChannelClosed:
            bridge.send()  # the last batch; then the helper ends
            raise
        out.write(first)
        rest = handoff.read_many()
        if rest:
            out.write_many(rest)
        bridge.send()

    def body() -> None:
        handoff.write(control())

    return Coupling("send-buffered", body,
                    helpers=[_Pump(forward, name="send-buffered:srt")],
                    channels={"handoff": handoff, "out": out},
                    closers=[handoff.close], period=period, cycles=cycles, priority=priority)


def send_sampled(
    bridge: Bridge,
    topic: str,
    msg_type: str,
    control: SendLaw,
    *,
    rate_hz: float = 100.0,
    field: str | None = "data",
    transport: Transport = "udp",
    period: float = 0.001,
    cycles: int | None = None,
    priority: bool = True,
) -> Coupling:
    """Figure 5.6: send a sub-sample at ``rate_hz`` from a lower-priority timed process.

    The loop writes a non-blocking local channel of size 1 (the latest value wins); the
    helper wakes at ``rate_hz``, reads the latest value, writes it to a ``through_buffer``
    bridge channel and calls ``bridge.send()``. ``channels``: ``"handoff"``, ``"out"``.
    """
    out = bridge.publish(topic, msg_type, field, transport=transport, through_buffer=True)
    handoff: Channel[Any] = Channel(1, blocking=False, name=f"{topic} sample")

    def forward() -> None:
        try:
            value = handoff.read()
        except NoValueYet:
            return
        out.write(value)
        bridge.send()

    def body() -> None:
        handoff.write(control())

    return Coupling("send-sampled", body,
                    helpers=[_Ticker(forward, rate_hz, name="send-sampled:srt")],
                    channels={"handoff": handoff, "out": out},
                    closers=[handoff.close], period=period, cycles=cycles, priority=priority)


def send_loop(
    bridge: Bridge,
    topic: str,
    msg_type: str,
    control: SendLaw,
    *,
    field: str | None = "data",
    transport: Transport = "udp",
    buffer_size: int = 1024,
    period: float = 0.001,
    cycles: int | None = None,
    priority: bool = True,
) -> Coupling:
    """Figure 5.10: the loop writes a ``through_buffer`` channel; the SDK's send loop sends.

    The bridge must have been opened with ``Bridge.connect(send_rate_hz=...)``; values then
    leave at that rate in one packet per tick, and the loop's write is a ring operation only.
    """
    if bridge.send_rate_hz is None:
        raise ValueError("send_loop needs a bridge opened with Bridge.connect(send_rate_hz=...)"
                         "; without it buffered values wait for an explicit bridge.send()")
    out = bridge.publish(topic, msg_type, field, transport=transport, through_buffer=True,
                         buffer_size=buffer_size)

    def body() -> None:
        out.write(control())

    return Coupling(f"send-loop-{bridge.send_rate_hz:g}hz", body, channels={"out": out},
                    period=period, cycles=cycles, priority=priority)
