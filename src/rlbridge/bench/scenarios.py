"""Transports across the emulated link, and how one run of a stream there is summarised.

``rlbridge bench latency --transport/--delay/--loss`` measures one condition of the user's
choosing; the thesis's own list of conditions is the research suite's
(``benchmarks/evaluation/scenarios.py``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from rlbridge.bench.common import percentile


@dataclass(frozen=True)
class Transport:
    key: str
    label: str
    transport: str
    nodelay: bool


TRANSPORTS = (
    Transport("tcp", "TCP+Nagle", "tcp", False),
    Transport("tcpn", "TCPn", "tcp", True),
    Transport("udp", "UDP", "udp", False),
)


@dataclass
class Summary:
    """The per-scenario table's columns for one run (latencies in ms)."""

    samples: int
    received: int
    lost: int
    p50: float
    p99: float
    max: float
    delayed: int
    within_1ms: int
    #: Most consecutive samples delayed by more than one period (the thesis's bursts).
    longest_burst: int = 0

    @property
    def delayed_pct(self) -> float:
        return 100.0 * self.delayed / self.received if self.received else math.nan

    @property
    def within_pct(self) -> float:
        return 100.0 * self.within_1ms / self.received if self.received else math.nan


def summarise(latencies_ms: Sequence[float | None], *, delay_ms: float, period_ms: float,
              sent: int | None = None) -> Summary:
    """``delayed``: later than the link delay plus one sample period (the next value was due).

    ``within_1ms``: between the link delay and the delay + 1 ms (the thesis's band for
    TCPn and UDP). ``sent`` counts values whose arrival order is unknown (baselines).
    """
    got = sorted(x for x in latencies_ms if x is not None)
    total = sent if sent is not None else len(latencies_ms)
    burst = longest = 0
    for x in latencies_ms:
        burst = burst + 1 if x is not None and x > delay_ms + period_ms else 0
        longest = max(longest, burst)
    return Summary(
        samples=total, received=len(got), lost=total - len(got),
        p50=percentile(got, 50), p99=percentile(got, 99), max=got[-1] if got else math.nan,
        delayed=sum(x > delay_ms + period_ms for x in got),
        within_1ms=sum(delay_ms <= x <= delay_ms + 1.0 for x in got), longest_burst=longest,
    )
