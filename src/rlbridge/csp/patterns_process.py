"""The proper coupling patterns with the HRT loop in its own process (``layout="process"``).

Each function mirrors its namesake in :mod:`rlbridge.csp.patterns` and is what that one
returns by default. The loop process does one shared-memory operation per cycle around the
control law (a slot read, or a ring push); everything that waits, wakes per value or touches
the bridge is an SRT helper thread of *this* process:

======================  ========================================================================
pattern (thesis)        SRT helper in this process
======================  ========================================================================
receive non-blocking    a pump blocks on a size-1 channel (only the newest value is kept) and
(5.3)                   puts each value into the slot as it arrives
receive blocking (5.4)  a pump blocks on a buffered channel (``buffer_size`` values of slack),
                        applies ``process`` and puts every value into the slot as it arrives
send buffered (5.5)     a ticker at the loop's rate drains the ring (every value, in order)
                        into a ``through_buffer`` channel and calls ``bridge.send()``
send sampled (5.6)      a ticker at ``rate_hz`` drains the ring and sends the newest value
send loop (5.10)        a ticker at the bridge's send rate drains the ring into a
                        ``through_buffer`` channel; the SDK's send loop sends it
======================  ========================================================================

Why helpers poll the ring instead of being woken: a wake-up is a system call in the loop, the
one thing the loop must never do for the network. A full ring refuses the value and counts it
(``loop_info["ring_dropped"]``); size it with ``buffer_size`` for the helper's period.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from typing import Any

from rlbridge.csp.bridge import Bridge
from rlbridge.csp.bridge_channels import IncomingChannel, OutgoingChannel
from rlbridge.csp.channel import Channel
from rlbridge.csp.connection import ConnectionClosed
from rlbridge.csp.coupling import LoopOptions, Pump, Ticker
from rlbridge.csp.isolated import IsolatedCoupling, LoopKind, LoopSpec, check_picklable
from rlbridge.csp.options import Transport
from rlbridge.csp.process import Process
from rlbridge.csp.shm import ShmLink

__all__ = ["receive_blocking", "receive_nonblocking", "send_buffered", "send_loop",
           "send_sampled"]


def unsubscriber(bridge: Bridge, channel: IncomingChannel) -> Callable[[], None]:
    """Close an incoming channel (waking a blocked reader) and unbind it on the server."""

    def close() -> None:
        channel.close()  # first: it must happen even when the link is already gone
        with contextlib.suppress(ConnectionClosed, OSError):
            bridge.unsubscribe(channel)

    return close


def _spec(name: str, kind: LoopKind, control: object, loop: LoopOptions) -> LoopSpec:
    """The loop's spec; refuses a law that cannot cross before anything is created."""
    check_picklable(control, name)
    return LoopSpec(name, kind, **loop)


def _new_link(closers: Sequence[Callable[[], None]], inputs: int, outputs: int,
              capacity: int = 1) -> ShmLink:
    """The segment, created after the channels; undo those if it cannot be made."""
    try:
        return ShmLink.create(inputs, outputs, capacity)
    except BaseException:
        for close in closers:
            close()
        raise


def _rate(loop: LoopOptions) -> float:
    return 1.0 / loop.get("period", 0.001)


def _coupling(spec: LoopSpec, control: Callable[..., Any], link: ShmLink, *,
              helpers: Sequence[Process], channels: dict[str, Channel[Any] | OutgoingChannel],
              closers: Sequence[Callable[[], None]] = (),
              finish: Callable[[], None] | None = None) -> IsolatedCoupling:
    try:
        return IsolatedCoupling(spec, control, link, helpers=helpers, finish=finish,
                                channels=channels, closers=closers)
    except BaseException:
        for close in closers:
            close()
        link.close()
        raise


# -- receive -------------------------------------------------------------------------------------


def receive_nonblocking(bridge: Bridge, topic: str, msg_type: str,
                        control: Callable[[float], object], *, field: str | None,
                        transport: Transport, initial: Any, loop: LoopOptions
                        ) -> IsolatedCoupling:
    """Figure 5.3 across processes: the loop reads a latest-value slot every cycle.

    The slot is filled as values arrive (a helper blocked on a size-1 channel, which keeps
    only the newest), not polled at the loop's rate: a poller would add up to a period of
    latency and wake this process once per loop cycle for nothing.
    """
    return _fed_by_arrival("receive-nonblocking", bridge, topic, msg_type, control,
                           field=field, transport=transport, buffer_size=1, process=None,
                           initial=initial, loop=loop)


def receive_blocking(bridge: Bridge, topic: str, msg_type: str,
                     control: Callable[[float], object], *, field: str | None,
                     transport: Transport, buffer_size: int,
                     process: Callable[[Any], Any] | None, initial: Any, loop: LoopOptions
                     ) -> IsolatedCoupling:
    """Figure 5.4 across processes: a pump puts every (processed) value into the slot."""
    return _fed_by_arrival("receive-blocking", bridge, topic, msg_type, control, field=field,
                           transport=transport, buffer_size=buffer_size, process=process,
                           initial=initial, loop=loop)


def _fed_by_arrival(name: str, bridge: Bridge, topic: str, msg_type: str,
                    control: Callable[[float], object], *, field: str | None,
                    transport: Transport, buffer_size: int,
                    process: Callable[[Any], Any] | None, initial: Any, loop: LoopOptions
                    ) -> IsolatedCoupling:
    """A loop reading slot 0, which a helper blocked on the bridge channel keeps current."""
    spec = _spec(name, "receive", control, loop)
    incoming = bridge.subscribe(topic, msg_type, field, transport=transport, blocking=True,
                                buffer_size=buffer_size)
    closers = [unsubscriber(bridge, incoming)]
    link = _new_link(closers, 1, 0)
    link.put(0, float(initial))
    read, put = incoming.read, link.put

    def forward() -> None:
        value = read()
        put(0, float(value if process is None else process(value)))

    return _coupling(spec, control, link, helpers=[Pump(forward, name=f"{name}:srt")],
                     channels={"in": incoming}, closers=closers)


# -- send ----------------------------------------------------------------------------------------


def _drainer(link: ShmLink, out: OutgoingChannel,
             send: Callable[[], object] | None) -> Callable[[], None]:
    """Move everything the loop pushed into ``out`` (then ``send()`` it, if given)."""
    drain, write_many = link.drain, out.write_many

    def step() -> None:
        values = drain(0)
        if values:
            write_many(values)
            if send is not None:
                send()

    return step


def send_buffered(bridge: Bridge, topic: str, msg_type: str, control: Callable[[], float],
                  *, field: str | None, transport: Transport, buffer_size: int,
                  loop: LoopOptions) -> IsolatedCoupling:
    """Figure 5.5 across processes: every value, in order, drained at the loop's rate."""
    spec = _spec("send-buffered", "send", control, loop)
    capacity = max(buffer_size, 1024)
    out = bridge.publish(topic, msg_type, field, transport=transport, through_buffer=True,
                         buffer_size=capacity)
    link = _new_link((), 0, 1, capacity)
    step = _drainer(link, out, bridge.send)
    return _coupling(spec, control, link,
                     helpers=[Ticker(step, _rate(loop), name="send-buffered:srt")],
                     channels={"out": out}, finish=step)


def send_sampled(bridge: Bridge, topic: str, msg_type: str, control: Callable[[], float],
                 *, rate_hz: float, field: str | None, transport: Transport,
                 loop: LoopOptions) -> IsolatedCoupling:
    """Figure 5.6 across processes: at ``rate_hz`` the newest value the loop pushed is sent."""
    spec = _spec("send-sampled", "send", control, loop)
    out = bridge.publish(topic, msg_type, field, transport=transport, through_buffer=True)
    # the ring holds what the loop pushes between two samples, with room to spare
    capacity = max(64, 4 * int(_rate(loop) / rate_hz) + 1)
    link = _new_link((), 0, 1, capacity)
    drain, write = link.drain, out.write

    def sample() -> None:
        values = drain(0)
        if values:
            write(values[-1])
            bridge.send()

    return _coupling(spec, control, link,
                     helpers=[Ticker(sample, rate_hz, name="send-sampled:srt")],
                     channels={"out": out})


def send_loop(bridge: Bridge, topic: str, msg_type: str, control: Callable[[], float], *,
              field: str | None, transport: Transport, buffer_size: int, loop: LoopOptions
              ) -> IsolatedCoupling:
    """Figure 5.10 across processes: the ring is drained into the SDK send loop's buffer."""
    rate = bridge.send_rate_hz
    if rate is None:
        raise ValueError("send_loop needs a bridge opened with Bridge.connect(send_rate_hz=...)"
                         "; without it buffered values wait for an explicit bridge.send()")
    spec = _spec(f"send-loop-{rate:g}hz", "send", control, loop)
    out = bridge.publish(topic, msg_type, field, transport=transport, through_buffer=True,
                         buffer_size=buffer_size)
    link = _new_link((), 0, 1, max(buffer_size, 1024))
    step = _drainer(link, out, None)
    return _coupling(spec, control, link,
                     helpers=[Ticker(step, rate, name=f"send-loop-{rate:g}hz:srt")],
                     channels={"out": out}, finish=step)
