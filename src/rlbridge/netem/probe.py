"""Measure a link: UDP round trips and the relay's own overhead.

Two harnesses:

* :func:`udp_ping_pong` drives both sockets from one thread, so one clock times both
  ends (used by the tests for one-way delays)::

      t0  sock_a.sendto(seq) --link--> sock_b.recvfrom
          sock_b.sendto(seq) --link--> sock_a.recv     t1     rtt = t1 - t0

* :func:`udp_ping` against an echo *process* (:func:`echo_process`), which is how real
  programs talk: every hop wakes up a process.  :func:`measure_overhead` runs it twice,
  through the link to an echo in namespace B and over ``lo`` to an echo in namespace A.
  Both paths pay the same process wake-ups; the difference is what the relay adds (two
  relay hops per round trip).  This mirrors the thesis's "reference measurement"
  (figure A.2), which it compared with the latencies measured under netem.
"""

from __future__ import annotations

import contextlib
import socket
import statistics
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass

from rlbridge.netem.link import EmulatedLink
from rlbridge.netem.link_settings import Side

_SEQ = struct.Struct("!I")


class ProbeError(RuntimeError):
    """A measurement could not be set up (its echo process did not start)."""


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
    budget_s: float = 120.0,
) -> list[float]:
    """RTTs (seconds) of up to ``count`` pings from ``sock_a`` to bound ``sock_b`` and back.

    Lost pings are left out; stale answers to earlier (timed-out) pings are skipped by
    sequence number.  Stops early once ``budget_s`` has passed.
    """
    if payload < _SEQ.size:
        raise ValueError(f"payload must be at least {_SEQ.size} bytes")
    target = sock_b.getsockname()
    padding = bytes(payload - _SEQ.size)
    rtts: list[float] = []
    give_up = time.monotonic() + budget_s
    for seq in range(count):
        if time.monotonic() > give_up:
            break
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


def udp_ping(
    sock: socket.socket,
    target: tuple[str, int],
    *,
    count: int,
    payload: int = 32,
    interval_s: float = 0.0,
    timeout_s: float = 1.0,
    budget_s: float = 120.0,
) -> list[float]:
    """RTTs (seconds) of up to ``count`` pings from ``sock`` to an echo at ``target``.

    Lost pings are left out.  Stops early once ``budget_s`` has passed, so a dead echo
    costs at most that long, not ``count * timeout_s``.
    """
    if payload < _SEQ.size:
        raise ValueError(f"payload must be at least {_SEQ.size} bytes")
    padding = bytes(payload - _SEQ.size)
    rtts: list[float] = []
    give_up = time.monotonic() + budget_s
    for seq in range(count):
        if time.monotonic() > give_up:
            break
        start = time.perf_counter()
        sock.sendto(_SEQ.pack(seq) + padding, target)
        if _receive_seq(sock, seq, timeout_s) is not None:
            rtts.append(time.perf_counter() - start)
        if interval_s > 0.0:
            time.sleep(interval_s)
    return rtts


_ECHO_SCRIPT = """
import select, socket, sys, time
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind((sys.argv[1], 0))
print(s.getsockname()[1], flush=True)
deadline = time.monotonic() + float(sys.argv[2])
while (left := deadline - time.monotonic()) > 0:
    ready, _, _ = select.select([s, sys.stdin], [], [], left)
    if sys.stdin in ready:
        break  # EOF: the parent is done with us (or died)
    if s in ready:
        data, peer = s.recvfrom(65536)
        s.sendto(data, peer)
"""


@contextlib.contextmanager
def echo_process(
    link: EmulatedLink, side: Side, host: str, *, max_lifetime_s: float = 600.0
) -> Iterator[tuple[str, int]]:
    """A UDP echo process in ``side``'s namespace bound to ``host``; yields its address.

    The process lives until the block ends (its stdin is closed), at most
    ``max_lifetime_s``; the link terminates it on close in any case.
    """
    proc = link.popen_in(
        side,
        [sys.executable, "-c", _ECHO_SCRIPT, host, repr(max_lifetime_s)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        if not line.strip().isdigit():
            raise ProbeError(f"echo process in namespace {side} did not start: {line!r}")
        yield host, int(line)
    finally:
        if proc.stdin is not None:
            proc.stdin.close()
        try:
            proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


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


def measure_overhead(
    link: EmulatedLink, *, count: int = 1000, payload: int = 32, interval_s: float = 0.0
) -> Overhead:
    """Ping an echo process through the link and one over ``lo`` in namespace A; compare.

    The link's impairments are left as they are: on a clean link the difference is the
    relay's own overhead; with a delay ``d`` it is ``2 d`` plus that overhead.  The mean
    relay lateness covers the packets of this measurement, the maximum the link's life.
    """
    with (
        echo_process(link, "b", link.addr_b) as far,
        echo_process(link, "a", "127.0.0.1") as near,
        link.open_socket("a") as through,
        link.open_socket("a") as loop,
    ):
        through.bind((link.addr_a, 0))
        loop.bind(("127.0.0.1", 0))
        before = link.stats()
        rtts_link = udp_ping(through, far, count=count, payload=payload, interval_s=interval_s)
        after = link.stats()
        rtts_lo = udp_ping(loop, near, count=count, payload=payload, interval_s=interval_s)
    pairs = ((before.a_to_b, after.a_to_b), (before.b_to_a, after.b_to_a))
    delivered = sum(new.delivered - old.delivered for old, new in pairs)
    late_sum = sum(
        new.late_mean_us * new.delivered - old.late_mean_us * old.delivered for old, new in pairs
    )
    return Overhead(
        link=summarize(rtts_link, count),
        loopback=summarize(rtts_lo, count),
        relay_late_mean_us=late_sum / delivered if delivered else 0.0,
        relay_late_max_us=max(after.a_to_b.late_max_us, after.b_to_a.late_max_us),
    )
