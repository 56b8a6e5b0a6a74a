"""``python -m benchmarks.evaluation``: every network scenario of the thesis in one run.

One :class:`~rlbridge.netem.EmulatedLink` carries every latency run: for each scenario the
link is re-impaired (data direction only, as the thesis's port filter did), then each row runs
in fresh processes: rlbridge over TCP+Nagle, TCPn and UDP, the same stream through ZeroMQ and
Zenoh, and the channel-policy rows this build supports. The throughput tables 3.1/3.2 run on
loopback (the emulator's Python relay tops out near 20 000 packets/s, below the bridge).
Rows run once each (a repeat of the whole evaluation costs ~10 minutes); the machine's load is
recorded beside the figures so that a noisy run can be recognised.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from benchmarks.evaluation import policies
from benchmarks.evaluation.scenarios import QUICK_SCENARIOS, SCENARIOS, Scenario
from rlbridge.bench import baselines
from rlbridge.bench.common import BenchError, Link, LoopbackLink, ProcessGroup, Skipped, run_flow
from rlbridge.bench.netpath import PriorityLink, StreamResult, StreamSpec, measure_stream
from rlbridge.bench.scenarios import TRANSPORTS, Summary, summarise

if TYPE_CHECKING:
    from rlbridge.netem import EmulatedLink

RATE_HZ = 100.0
PERIOD_MS = 1000.0 / RATE_HZ
#: Scenarios that also run the baselines (ZeroMQ, Zenoh) and the policy rows.
BASELINE_SCENARIOS = ("reference", "delay7.5", "delay15", "loss1")
POLICY_SCENARIOS = ("delay7.5", "loss1")
THROUGHPUT_RATES = (100, 250, 500, 1000, 2000, 5000, 10_000, 20_000, 50_000, 100_000,
                    200_000, 500_000, 1_000_000)
Progress = Callable[[str], None]


@dataclass(frozen=True)
class EvalSettings:
    count: int = 1000
    quick: bool = False
    seed: int = 1
    throughput_seconds: float = 1.0
    #: SCHED_FIFO priority of the measured processes in latency rows (0: normal scheduling).
    rt_priority: int = 5

    @property
    def scenarios(self) -> tuple[Scenario, ...]:
        return tuple(s for s in SCENARIOS if not self.quick or s.key in QUICK_SCENARIOS)


@dataclass
class Row:
    """One measured (or skipped) row of a scenario's table."""

    scenario: str
    key: str
    label: str
    kind: str  # rlbridge | baseline | policy
    summary: Summary | None = None
    latencies_ms: list[float | None] = field(default_factory=list)
    note: str = ""
    bytes_per_value: float = math.nan
    flagged_old: int | None = None
    relay_late_over_1ms: int = 0
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class ThroughputPoint:
    direction: str
    transport: str
    offered_hz: int
    sent_per_s: float
    received_per_s: float
    lost: int
    sent: int


@dataclass
class Evaluation:
    rows: list[Row] = field(default_factory=list)
    throughput: list[ThroughputPoint] = field(default_factory=list)
    load: list[tuple[str, tuple[float, float, float]]] = field(default_factory=list)

    def note_load(self, when: str) -> None:
        self.load.append((when, os.getloadavg()))


# -- latency rows ----------------------------------------------------------------------------
def _bridge_row(link: Link, emulated: EmulatedLink, sc: Scenario, key: str, label: str,
                kind: str, spec: StreamSpec, age_limit: float | None = None) -> Row:
    before = emulated.stats()
    res = measure_stream(link, spec)
    after = emulated.stats()
    data = "a_to_b" if spec.direction == "down" else "b_to_a"
    d0, d1 = getattr(before, data), getattr(after, data)
    lat = res.latencies_ms
    row = Row(sc.key, key, label, kind,
              summarise(lat, delay_ms=sc.delay_ms, period_ms=PERIOD_MS), lat,
              bytes_per_value=(d1.bytes_delivered - d0.bytes_delivered) / len(res.sent_ns),
              relay_late_over_1ms=d1.late_over_1ms - d0.late_over_1ms,
              extra={**res.extra, "duplicates": res.duplicates})
    if age_limit is not None:
        row.flagged_old = res.flagged_old
    return row


def _baseline_row(link: Link, sc: Scenario, kind: str, count: int) -> Row:
    label = {"zmq": "ZeroMQ PUB/SUB (tcp)", "zenoh": "Zenoh peer (tcp)"}[kind]
    mode = {"mode": "paced", "rate_hz": RATE_HZ, "count": count, "idle_s": 1.5}
    with ProcessGroup(link, lifetime_s=count / RATE_HZ + 180) as group:
        try:
            tx, rx = baselines.spawn_pair(group, kind, mode, rx_side="b")
            flow = run_flow(tx, rx, [tx, rx], count / RATE_HZ + 60)
        except Skipped as exc:
            return Row(sc.key, kind, label, "baseline", note=f"skipped: {exc}")
        except BenchError as exc:
            raise BenchError(f"{exc}{group.diagnostics()}") from None
    lat: list[float | None] = [ns / 1e6 for ns in flow.received["samples"]]
    sent = int(flow.sent["sent"])
    return Row(sc.key, kind, label, "baseline",
               summarise(lat, delay_ms=sc.delay_ms, period_ms=PERIOD_MS, sent=sent), lat)


def _scenario_rows(link: Link, emulated: EmulatedLink, sc: Scenario, settings: EvalSettings,
                   progress: Progress) -> list[Row]:
    rows: list[Row] = []
    for t in TRANSPORTS:
        progress(f"{sc.key}: {t.label}")
        spec = StreamSpec(sc.direction, t.transport, t.nodelay, RATE_HZ, settings.count,
                          send_rate_hz=sc.send_rate_hz)
        rows.append(_bridge_row(link, emulated, sc, t.key, t.label, "rlbridge", spec))
    if sc.key in BASELINE_SCENARIOS:
        for kind in ("zmq", "zenoh"):
            progress(f"{sc.key}: {kind}")
            rows.append(_baseline_row(link, sc, kind, settings.count))
    if sc.key in POLICY_SCENARIOS:
        for pr in policies.policy_rows(sc.delay_ms):
            reason = policies.availability(pr)
            if reason is not None:
                rows.append(Row(sc.key, pr.key, pr.label, "policy", note=reason))
                continue
            progress(f"{sc.key}: {pr.label}")
            spec = StreamSpec("down", pr.transport, pr.nodelay, RATE_HZ, settings.count,
                              policy=pr.policy, age_limit_ms=pr.age_limit_ms)
            try:
                rows.append(_bridge_row(link, emulated, sc, pr.key, pr.label, "policy", spec,
                                        pr.age_limit_ms))
            except BenchError as exc:  # a policy that exists but fails is shown, not hidden
                rows.append(Row(sc.key, pr.key, pr.label, "policy",
                                note=f"error: {str(exc).splitlines()[0]}"))
    return rows


def run_latency(settings: EvalSettings, ev: Evaluation, progress: Progress) -> None:
    from rlbridge.netem import emulator_unavailable_reason

    reason = emulator_unavailable_reason()
    if reason is not None:
        raise BenchError(f"the network emulator cannot run here: {reason}")
    # SCHED_FIFO relay: its wake-ups are then not queued behind the measured processes
    # (docs/netem.md: mean lateness ~430 us -> ~100 us under load).
    from rlbridge.netem import EmulatedLink

    with EmulatedLink(seed=settings.seed, relay_rt_priority=10,
                      max_lifetime_s=3000.0) as emulated:
        link: Link = (PriorityLink(emulated, settings.rt_priority) if settings.rt_priority
                      else emulated)
        for sc in settings.scenarios:
            emulated.set_impairment(delay_ms=sc.delay_ms, loss_pct=sc.loss_pct,
                                direction=sc.link_direction)  # type: ignore[arg-type]
            ev.rows += _scenario_rows(link, emulated, sc, settings, progress)
            ev.note_load(f"after {sc.key}")


# -- throughput (tables 3.1 / 3.2, continued upward) --------------------------------------------
def _throughput_point(link: Link, direction: str, transport: str, rate: int,
                      seconds: float) -> ThroughputPoint:
    count = max(200, int(rate * seconds))
    res: StreamResult = measure_stream(link, StreamSpec(direction, transport, True,
                                                        float(rate), count))
    arrivals = [r for r in res.recv_ns if r is not None]
    span = (max(arrivals) - res.sent_ns[0]) / 1e9 if arrivals else math.nan
    return ThroughputPoint(direction, transport, rate, res.send_rate,
                           len(arrivals) / span if arrivals else 0.0, res.lost, count)


def saturated(p: ThroughputPoint) -> bool:
    """Stop the series: under 90 % of what was sent arrives per second, > 1 % is lost, or the
    sender itself reaches under half the offered rate.

    Judged against the achieved send rate, not the offered one, so that a sender slowed a
    little by other jobs on the machine does not end the series early.
    """
    return (p.received_per_s < 0.9 * p.sent_per_s or p.lost > 0.01 * p.sent
            or p.sent_per_s < 0.5 * p.offered_hz)


def run_throughput(settings: EvalSettings, ev: Evaluation, progress: Progress) -> None:
    link = LoopbackLink()
    rates = THROUGHPUT_RATES[:8] if settings.quick else THROUGHPUT_RATES
    seconds = settings.throughput_seconds / (2 if settings.quick else 1)
    for direction in ("up", "down"):
        for transport in ("udp", "tcp"):
            for rate in rates:
                progress(f"throughput {direction} {transport} {rate} Hz")
                p = _throughput_point(link, direction, transport, rate, seconds)
                ev.throughput.append(p)
                if saturated(p):
                    break
    ev.note_load("after throughput")


def run(settings: EvalSettings, progress: Progress) -> Evaluation:
    ev = Evaluation()
    ev.note_load("start")
    run_latency(settings, ev, progress)
    run_throughput(settings, ev, progress)
    return ev
