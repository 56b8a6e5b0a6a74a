"""Coupling patterns between a hard-real-time loop and the bridge (thesis chapter 5).

Each function returns a :class:`~rlbridge.csp.coupling.Coupling`: an HRT
:class:`~rlbridge.csp.coupling.ControlLoop` (a timed, bounded recursion marked ``hrt``), the
lower-priority helper processes the pattern needs, and the channels it created, composed as
``PriParallel(loop, *helpers)`` so that the loop gets the highest priority the OS grants. The
control law is a plain callable; the recipe does the plumbing. Every recipe takes the loop's
options as keywords (:class:`~rlbridge.csp.coupling.LoopOptions`: ``period``, ``cycles``,
``priority``, ``cpu``). A receive recipe's loop body is ``control(source.read())`` and a send
recipe's ``sink.write(control())``; they differ only in what ``source``/``sink`` is and which
helper sits behind it, which is what each function spells out.

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

Where the loop runs (``layout``). The five proper patterns (5.3, 5.4, 5.5, 5.6, 5.10) put
the loop in **its own OS process** by default (``layout="process"``,
:class:`~rlbridge.csp.isolated.IsolatedCoupling`): its interpreter holds nothing but the loop,
the bridge and the pattern's helpers stay in the calling process, values cross in shared
memory (:mod:`rlbridge.csp.patterns_process` says which helper does what). That is the layout
whose p99 jitter stayed at the loop-alone reference, where every in-process layout lost
+74 to +370 us to the GIL (docs/gil.md, docs/jitter.md). It asks two things of the control
law: it must be picklable (a module-level function or class instance; its state lives in the
loop process, :attr:`~rlbridge.csp.isolated.IsolatedCoupling.final_control` returns it), and
values are ``float64``. ``layout="thread"`` runs the loop as a thread of this process (any
callable, any value type), holding the GIL switch interval at :data:`HRT_SWITCH_INTERVAL`
(0.1 ms; loop option ``switch_interval``) while it runs. :data:`DEFAULT_LAYOUT` is
``"thread"`` on CPUs where the shared-memory link cannot run (not x86). The naive patterns
and :func:`reference` are in-process only: they exist to be compared.

In the thread layout every operation the loop does is a ring buffer operation (no lock, no
system call), except ringing a doorbell when a consumer sleeps (``send_buffered``,
``send_naive``); whatever waits (for the network, for a value) waits in a lower-priority
thread.

Lifetimes: a coupling owns the channels it created. When the loop has run its ``cycles`` (or
:meth:`Coupling.stop` is called) the run's stop event is set, its incoming bridge channels are
unsubscribed and its local channels closed, which wakes any helper blocked on them; then
``run()`` returns. Outgoing bridge channels stay bound until ``bridge.close()``, which flushes
them, so the last values written by the loop are not lost. A coupling runs once.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from rlbridge._compat import Unpack
from rlbridge.csp import patterns_process as isolated
from rlbridge.csp.bridge import Bridge
from rlbridge.csp.bridge_channels import OutgoingChannel
from rlbridge.csp.channel import Channel
from rlbridge.csp.coupling import (
    BaseCoupling,
    ControlLoop,
    Coupling,
    LoopOptions,
    Pump,
    Ticker,
)
from rlbridge.csp.gil import HRT_SWITCH_INTERVAL, realtime_switch_interval
from rlbridge.csp.isolated import DEFAULT_LAYOUT, IsolatedCoupling, Layout
from rlbridge.csp.options import Transport
from rlbridge.csp.patterns_process import unsubscriber
from rlbridge.csp.process import Process
from rlbridge.errors import ChannelClosed, NoValueYet

__all__ = [
    "DEFAULT_LAYOUT",
    "HRT_SWITCH_INTERVAL",
    "BaseCoupling",
    "ControlLoop",
    "Coupling",
    "IsolatedCoupling",
    "Layout",
    "LoopOptions",
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

Owned = dict[str, Channel[Any] | OutgoingChannel]


def _reading(name: str, source: Channel[Any], control: ReceiveLaw, loop: LoopOptions, *,
             channels: Owned, closers: Sequence[Callable[[], None]],
             helpers: Sequence[Process] = ()) -> Coupling:
    """The receive recipes' coupling: each cycle ``control(source.read())``."""
    read = source.read

    def body() -> None:
        control(read())

    return Coupling(name, body, helpers=helpers, channels=channels, closers=closers, **loop)


def _writing(name: str, sink: Channel[Any] | OutgoingChannel, control: SendLaw,
             loop: LoopOptions, *, channels: Owned, closers: Sequence[Callable[[], None]] = (),
             helpers: Sequence[Process] = ()) -> Coupling:
    """The send recipes' coupling: each cycle ``sink.write(control())``."""
    write = sink.write

    def body() -> None:
        write(control())

    return Coupling(name, body, helpers=helpers, channels=channels, closers=closers, **loop)


def _in_own_process(layout: Layout) -> bool:
    if layout not in ("process", "thread"):
        raise ValueError(f"layout must be 'process' or 'thread', got {layout!r}")
    return layout == "process"


# -- the baseline ------------------------------------------------------------------------------


def reference(control: Callable[[], object], **loop: Unpack[LoopOptions]) -> Coupling:
    """The loop alone (thesis figure 5.7): the baseline for every pattern, no bridge."""
    return Coupling("reference", control, **loop)


# -- receive patterns --------------------------------------------------------------------------


def receive_nonblocking(
    bridge: Bridge, topic: str, msg_type: str, control: ReceiveLaw, *,
    field: str | None = "data", transport: Transport = "udp", initial: Any = 0.0,
    layout: Layout = DEFAULT_LAYOUT, **loop: Unpack[LoopOptions],
) -> BaseCoupling:
    """Figure 5.3: the loop reads a non-blocking bridge channel of size 1 every cycle.

    The read is a ring operation; with nothing new it returns the latest value again (or
    ``initial``), so the loop never waits for the network. ``channels["in"]`` is the
    :class:`IncomingChannel` (``age_ns``, ``lost``, ``statistics()``).
    """
    if _in_own_process(layout):
        return isolated.receive_nonblocking(bridge, topic, msg_type, control, field=field,
                                            transport=transport, initial=initial, loop=loop)
    incoming = bridge.subscribe(topic, msg_type, field, transport=transport, blocking=False,
                                buffer_size=1, initial=initial)
    return _reading("receive-nonblocking", incoming, control, loop, channels={"in": incoming},
                    closers=[unsubscriber(bridge, incoming)])


def receive_blocking(
    bridge: Bridge, topic: str, msg_type: str, control: ReceiveLaw, *,
    field: str | None = "data", transport: Transport = "udp", buffer_size: int = 16,
    process: Callable[[Any], Any] | None = None, initial: Any = 0.0,
    layout: Layout = DEFAULT_LAYOUT, **loop: Unpack[LoopOptions],
) -> BaseCoupling:
    """Figure 5.4: a lower-priority process does the blocking read, the loop never waits.

    The helper reads every value from a blocking bridge channel (``buffer_size`` values of
    slack), applies ``process`` (a sanity check, a sequence controller; ``None`` = identity)
    and writes the result to a non-blocking local channel of size 1, which the loop reads.
    The helper's timing follows the message rate; the loop's follows its timer.
    ``channels``: ``"in"`` (bridge, blocking) and ``"handoff"`` (local, non-blocking).
    """
    if _in_own_process(layout):
        return isolated.receive_blocking(bridge, topic, msg_type, control, field=field,
                                         transport=transport, buffer_size=buffer_size,
                                         process=process, initial=initial, loop=loop)
    incoming = bridge.subscribe(topic, msg_type, field, transport=transport, blocking=True,
                                buffer_size=buffer_size)
    handoff: Channel[Any] = Channel(1, blocking=False, initial=initial,
                                    name=f"{topic} handoff")

    def forward() -> None:
        value = incoming.read()
        handoff.write(value if process is None else process(value))

    return _reading("receive-blocking", handoff, control, loop,
                    helpers=[Pump(forward, name="receive-blocking:srt")],
                    channels={"in": incoming, "handoff": handoff},
                    closers=[unsubscriber(bridge, incoming), handoff.close])


def receive_naive(
    bridge: Bridge, topic: str, msg_type: str, control: ReceiveLaw, *,
    field: str | None = "data", transport: Transport = "udp",
    **loop: Unpack[LoopOptions],
) -> Coupling:
    """For comparison only: the loop reads a *blocking* bridge channel directly.

    The loop then runs when messages arrive, not when its timer says (thesis 5.3.1: jitter
    up to one period, releases skipped). The channel reports it: a ``RealTimeWarning`` the
    first time and ``statistics().hrt_blocking_reads`` every time.
    """
    incoming = bridge.subscribe(topic, msg_type, field, transport=transport, blocking=True,
                                buffer_size=1)
    return _reading("receive-naive", incoming, control, loop, channels={"in": incoming},
                    closers=[unsubscriber(bridge, incoming)])


# -- send patterns -----------------------------------------------------------------------------


def send_naive(
    bridge: Bridge, topic: str, msg_type: str, control: SendLaw, *,
    field: str | None = "data", transport: Transport = "udp",
    **loop: Unpack[LoopOptions],
) -> Coupling:
    """For comparison: the loop writes an immediate bridge channel (``through_buffer=False``).

    No socket call happens in the loop (the SDK's send thread does it), but a write wakes that
    thread when it sleeps, which is a system call in the loop and a GIL competitor right after.
    """
    out = bridge.publish(topic, msg_type, field, transport=transport, through_buffer=False)
    return _writing("send-naive", out, control, loop, channels={"out": out})


def send_buffered(
    bridge: Bridge, topic: str, msg_type: str, control: SendLaw, *,
    field: str | None = "data", transport: Transport = "udp", buffer_size: int = 64,
    layout: Layout = DEFAULT_LAYOUT, **loop: Unpack[LoopOptions],
) -> BaseCoupling:
    """Figure 5.5: send every value, in order, through a lower-priority process.

    The loop writes a blocking buffered local channel (never blocks; overwrites and counts
    when ``buffer_size`` values pile up); the helper blocks reading it, moves everything it
    finds into a ``through_buffer`` bridge channel and calls ``bridge.send()``. At the end
    the helper drains the handoff before it stops, so no value written by the loop is lost.
    ``channels``: ``"handoff"`` (local) and ``"out"`` (bridge).
    """
    if _in_own_process(layout):
        return isolated.send_buffered(bridge, topic, msg_type, control, field=field,
                                      transport=transport, buffer_size=buffer_size, loop=loop)
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

    return _writing("send-buffered", handoff, control, loop,
                    helpers=[Pump(forward, name="send-buffered:srt")],
                    channels={"handoff": handoff, "out": out}, closers=[handoff.close])


def send_sampled(
    bridge: Bridge, topic: str, msg_type: str, control: SendLaw, *,
    rate_hz: float = 100.0, field: str | None = "data", transport: Transport = "udp",
    layout: Layout = DEFAULT_LAYOUT, **loop: Unpack[LoopOptions],
) -> BaseCoupling:
    """Figure 5.6: send a sub-sample at ``rate_hz`` from a lower-priority timed process.

    The loop writes a non-blocking local channel of size 1 (the latest value wins); the
    helper wakes at ``rate_hz``, reads the latest value, writes it to a ``through_buffer``
    bridge channel and calls ``bridge.send()``. ``channels``: ``"handoff"``, ``"out"``.
    """
    if _in_own_process(layout):
        return isolated.send_sampled(bridge, topic, msg_type, control, rate_hz=rate_hz,
                                     field=field, transport=transport, loop=loop)
    out = bridge.publish(topic, msg_type, field, transport=transport, through_buffer=True)
    handoff: Channel[Any] = Channel(1, blocking=False, name=f"{topic} sample")

    def forward() -> None:
        try:
            value = handoff.read()
        except NoValueYet:
            return
        out.write(value)
        bridge.send()

    return _writing("send-sampled", handoff, control, loop,
                    helpers=[Ticker(forward, rate_hz, name="send-sampled:srt")],
                    channels={"handoff": handoff, "out": out}, closers=[handoff.close])


def send_loop(
    bridge: Bridge, topic: str, msg_type: str, control: SendLaw, *,
    field: str | None = "data", transport: Transport = "udp", buffer_size: int = 1024,
    layout: Layout = DEFAULT_LAYOUT, **loop: Unpack[LoopOptions],
) -> BaseCoupling:
    """Figure 5.10: the loop writes a ``through_buffer`` channel; the SDK's send loop sends.

    The bridge must have been opened with ``Bridge.connect(send_rate_hz=...)``; values then
    leave at that rate in one packet per tick, and the loop's write is a ring operation only.
    """
    if _in_own_process(layout):
        return isolated.send_loop(bridge, topic, msg_type, control, field=field,
                                  transport=transport, buffer_size=buffer_size, loop=loop)
    if bridge.send_rate_hz is None:
        raise ValueError("send_loop needs a bridge opened with Bridge.connect(send_rate_hz=...)"
                         "; without it buffered values wait for an explicit bridge.send()")
    out = bridge.publish(topic, msg_type, field, transport=transport, through_buffer=True,
                         buffer_size=buffer_size)
    return _writing(f"send-loop-{bridge.send_rate_hz:g}hz", out, control, loop,
                    channels={"out": out})
