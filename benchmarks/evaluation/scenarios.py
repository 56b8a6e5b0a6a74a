"""The thesis's network scenarios (appendix A, figures 4.2-4.4), as the evaluation runs them.

Every scenario is a 100 Hz set-point stream (``T_sample = 10 ms``) across the emulated link.
As in the thesis (listings A.1/A.2 filter on the sender's port) only the data direction is
impaired; the acknowledgements and heartbeats coming back cross a clean path. How one run is
summarised is the package's (:mod:`rlbridge.bench.scenarios`), shared with
``rlbridge bench latency --delay/--loss``.
"""

from __future__ import annotations

from dataclasses import dataclass


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
