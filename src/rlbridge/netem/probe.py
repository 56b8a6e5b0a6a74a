"""Measure a link: UDP ping-pong RTTs and the relay's own overhead.

Both sockets live in this process and are driven by one thread, so one clock times both
ends and no echo server (and no extra process wake-up) is involved::

    t0  sock_a.sendto(seq) --link--> sock_b.recvfrom
        sock_b.sendto(seq) --link--> sock_a.recv     t1     rtt = t1 - t0

The same function run on two sockets on ``lo`` inside namespace A gives the reference
(the kernel and Python cost of the harness itself); the difference is what the relay
adds.  This mirrors the thesis's "reference measurement" (figure A.2), which it
subtracted from the latencies measured with netem.
"""

from __future__ import annotations

import socket
import statistics
import struct
import time
from dataclasses import dataclass

from rlbridge.netem.link import EmulatedLink

_SEQ = struct.Struct("!I")


@dataclass(frozen=True)
class RttSummary:
    """RTT statistics in microseconds; ``lost`` pings got no answer within the timeout."""

    sent: int
    lost: int
    min_us: float
    median_us: float
    p99_us: float
    max_us: float

    def __str__(self) -> str:
        return (
            f"n={self.sent - self.lost}/{self.sent} min {self.min_us:.0f} us, "
            f"median {self.median_us:.0f} us, p99 {self.p99_us:.0f} us, max {self.max_us:.0f} us"
        )


def summarize(rtts_s: list[float], sent: int) -> RttSummary:
    """Summarise RTTs given in seconds."""
    if not rtts_s:
        nan = float("nan")
        return RttSummary(sent, sent, nan, nan, nan, nan)
    us = sorted(r * 1e6 for r in rtts_s)
    p99 = us[min(len(us) - 1, int(0.99 * len(us)))]
    return RttSummary(sent, sent - len(us), us[0], statistics.median(us), p99, us[-1])


def udp_ping_pong(
    sock_a: socket.socket,
    sock_b: socket.socket,
    *,
    count: int,
    payload: int = 32,
    interval_s: float = 0.0,
    timeout_s: float = 1.0,
) -> list[float]:
    """RTTs (seconds) of ``count`` pings from ``sock_a`` to bound ``sock_b`` and back.

    Lost pings are left out; stale answers to earlier (timed-out) pings are skipped by
    sequence number.  Runtime is bounded by ``count * (interval_s + 2 * timeout_s)``.
    """
    if payload < _SEQ.size:
        raise ValueError(f"payload must be at least {_SEQ.size} bytes")
    target = sock_b.getsockname()
    padding = bytes(payload - _SEQ.size)
    rtts: list[float] = []
    for seq in range(count):
        message = _SEQ.pack(seq) + padding
        start = time.perf_counter()
        sock_a.sendto(message, target)
        reply_to = _receive_seq(sock_b, seq, timeout_s)
        if reply_to is None:
            continue
        sock_b.sendto(message, reply_to)
        if _receive_seq(sock_a, seq, timeout_s) is not None:
            rtts.append(time.perf_counter() - start)
        if interval_s > 0.0:
            time.sleep(interval_s)
    return rtts


def _receive_seq(sock: socket.socket, seq: int, timeout_s: float) -> tuple[str, int] | None:
    """Wait for the datagram carrying ``seq``; return its sender, or None on timeout."""
    deadline = time.monotonic() + timeout_s
    while (remaining := deadline - time.monotonic()) > 0.0:
        sock.settimeout(remaining)
        try:
            data, sender = sock.recvfrom(65536)
        except TimeoutError:
            return None
        if len(data) >= _SEQ.size and _SEQ.unpack_from(data)[0] == seq:
            host, port = sender[0], sender[1]
            return str(host), int(port)
    return None


@dataclass(frozen=True)
class Overhead:
    """What the relay adds to a round trip, measured against ``lo`` in namespace A."""

    link: RttSummary
    loopback: RttSummary
    relay_late_mean_us: float
    relay_late_max_us: float

    @property
    def added_median_us(self) -> float:
        """Median RTT through the link minus median RTT over loopback (two relay hops)."""
        return self.link.median_us - self.loopback.median_us


def measure_overhead(link: EmulatedLink, *, count: int = 1000, payload: int = 32) -> Overhead:
    """Ping-pong through the (clean) link and over ``lo`` in namespace A, and compare.

    The link's impairments are left as they are; call it on a link with none for the
    relay's own overhead.
    """
    with (
        link.open_socket("a") as a,
        link.open_socket("b") as b,
        link.open_socket("a") as lo_a,
        link.open_socket("a") as lo_b,
    ):
        a.bind((link.addr_a, 0))
        b.bind((link.addr_b, 0))
        lo_a.bind(("127.0.0.1", 0))
        lo_b.bind(("127.0.0.1", 0))
        before = link.stats()
        through = udp_ping_pong(a, b, count=count, payload=payload)
        after = link.stats()
        loopback = udp_ping_pong(lo_a, lo_b, count=count, payload=payload)
    late_max = max(after.a_to_b.late_max_us, after.b_to_a.late_max_us)
    delivered = (after.a_to_b.delivered - before.a_to_b.delivered) + (
        after.b_to_a.delivered - before.b_to_a.delivered
    )
    late_sum = sum(
        s_after.late_mean_us * s_after.delivered - s_before.late_mean_us * s_before.delivered
        for s_before, s_after in (
            (before.a_to_b, after.a_to_b),
            (before.b_to_a, after.b_to_a),
        )
    )
    return Overhead(
        link=summarize(through, count),
        loopback=summarize(loopback, count),
        relay_late_mean_us=late_sum / delivered if delivered else 0.0,
        relay_late_max_us=late_max,
    )
