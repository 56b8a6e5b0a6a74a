"""The thesis's network scenarios (appendix A, figures 4.2-4.4) and how one run is summarised.

Every scenario is a 100 Hz set-point stream (``T_sample = 10 ms``) across the emulated link.
As in the thesis (listings A.1/A.2 filter on the sender's port) only the data direction is
impaired; the acknowledgements and heartbeats coming back cross a clean path.
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


@dataclass(frozen=True)
class Scenario:
    """One network condition; ``thesis`` quotes the thesis's figure per transport key."""

    key: str
    title: str
    figure: str
    delay_ms: float = 0.0
    loss_pct: float = 0.0
    direction: str = "down"
    send_rate_hz: float | None = None
    thesis: tuple[tuple[str, str], ...] = ()

    @property
    def link_direction(self) -> str:
        """The impaired direction of the link: the data's (server on a, client on b)."""
        return "a_to_b" if self.direction == "down" else "b_to_a"


SCENARIOS = (
    Scenario("reference", "Reference (no added delay or loss)", "A.2/A.3",
             thesis=(("all", "0.25 ms on average, A to D"),)),
    Scenario("delay3", "Delay 3 ms", "4.2a / A.4", delay_ms=3.0,
             thesis=(("tcp", "3-4 ms"), ("tcpn", "3-4 ms"), ("udp", "3-4 ms"))),
    Scenario("delay7.5", "Delay 7.5 ms", "4.2b / A.5", delay_ms=7.5,
             thesis=(("tcp", "12.5-27.5 ms"), ("tcpn", "7.5-8.5 ms"), ("udp", "7.5-8.5 ms"))),
    Scenario("delay15", "Delay 15 ms", "4.2c / A.6", delay_ms=15.0,
             thesis=(("tcp", "35-65 ms"), ("tcpn", "15-16 ms"), ("udp", "15-16 ms"))),
    Scenario("loss1", "Loss 1 %", "4.3 / A.7", loss_pct=1.0,
             thesis=(("tcp", "none lost, ~25 % of samples delayed, bursts ~20 samples wide"),
                     ("tcpn", "1 % lost (their bridge), samples before a loss 1-2 periods late"),
                     ("udp", "~1 % lost (10 of 1000), none delayed"))),
    Scenario("srt100", "SRT send loop at 100 Hz, control -> middleware", "4.4",
             direction="up", send_rate_hz=100.0,
             thesis=(("all", "network delay plus up to 1/f = 10 ms, saw-tooth"),)),
    Scenario("up-reference", "Control -> middleware without send loop (for 4.4)", "-",
             direction="up"),
)

QUICK_SCENARIOS = ("reference", "delay7.5", "loss1", "srt100")


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
