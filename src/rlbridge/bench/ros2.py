"""``rlbridge bench ros2``: values/s and latency through the ROS 2 adapter, next to rclpy itself.

Every row moves ``std_msgs/msg/Float64`` values between separate processes:

* ``rclpy``: a plain rclpy publisher node -> a plain rclpy subscriber node (1 hop, the
  baseline: what two ROS nodes written in Python get);
* ``in-tcp`` / ``in-udp``: rclpy publisher node -> ``rlbridge`` server (``--adapter ros2``) ->
  SDK subscriber, the server's channel to the SDK over TCP or UDP;
* ``out-tcp`` / ``out-udp``: SDK publisher -> server -> rclpy subscriber node.

Two measurements per row, each repeated and interleaved with the other rows so that a noisy
moment on a shared machine hits every row alike: **latency** of a paced stream (``rate`` Hz,
the value is the sender's ``time.time_ns()``, read back by the receiver the moment its callback
or blocking read gets it; same machine, same clock; Float64 holds it to 256 ns) and
**throughput** of a flood (the sender publishes as fast as it can for ``seconds``; values/s =
values received / (last arrival - first send)). Every value not received is counted.

The rclpy nodes are written as a ROS user would write them: one node, a
``SingleThreadedExecutor`` spun in a thread, one callback per message. QoS everywhere is
``KEEP_LAST(10)``, volatile; reliable, except that the server's endpoints of UDP channels are
best effort (the SDK's defaults), so the rclpy subscriber of ``out-udp`` is best effort too.
Before ``go`` the sender publishes warm-up values (-1) every 10 ms until the receiver has seen
one (DDS discovery is asynchronous); receivers ignore negative values.

The parent scopes DDS discovery for every process it starts: ``ROS_AUTOMATIC_DISCOVERY_RANGE``
defaults to ``LOCALHOST`` and ``ROS_DOMAIN_ID`` to one derived from its pid, unless set.
"""

from __future__ import annotations

import math
import os
import subprocess
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from rlbridge.bench.common import (
    STARTUP_S,
    BenchError,
    Link,
    Params,
    ProcessGroup,
    Side,
    fmt,
    markdown_table,
    median,
    percentile,
    ratio,
    report_header,
    run_flow,
    select_cases,
    start_server,
)
from rlbridge.bench.ros2_roles import DEPTH

#: The module whose ``ROLES`` the workers run.
MODULE = "rlbridge.bench.ros2_roles"
#: Samples each latency run drops at its start (first-touch allocation, matching settling).
WARMUP = 20
Mode = Literal["latency", "throughput"]


@dataclass(frozen=True)
class Case:
    """One row: who sends (``ros`` node or ``sdk``), who receives, the SDK's transport."""

    key: str
    label: str
    source: Literal["ros", "sdk"]
    sink: Literal["ros", "sdk"]
    transport: Literal["tcp", "udp"] = "tcp"


CASES = (
    Case("rclpy", "rclpy node -> rclpy node, 1 hop", "ros", "ros"),
    Case("in-tcp", "rclpy node -> bridge -> SDK, TCP", "ros", "sdk", "tcp"),
    Case("in-udp", "rclpy node -> bridge -> SDK, UDP", "ros", "sdk", "udp"),
    Case("out-tcp", "SDK -> bridge -> rclpy node, TCP", "sdk", "ros", "tcp"),
    Case("out-udp", "SDK -> bridge -> rclpy node, UDP", "sdk", "ros", "udp"),
)


# -- one measurement (parent) --------------------------------------------------------------
class RosScopedLink:
    """A link whose processes get the ROS discovery scope in their environment."""

    def __init__(self, inner: Link, env: Mapping[str, str]) -> None:
        self.inner = inner
        self.name = inner.name
        self.env = dict(env)

    def address(self, side: Side) -> str:
        return self.inner.address(side)

    def popen(self, side: Side, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[bytes]:
        return self.inner.popen(side, argv, env={**os.environ, **self.env}, **kwargs)


def ros_scope(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """Discovery on this machine and a domain of this run, unless the caller chose otherwise."""
    environ = os.environ if environ is None else environ
    return {
        "ROS_AUTOMATIC_DISCOVERY_RANGE": environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE",
                                                     "LOCALHOST"),
        "ROS_DOMAIN_ID": environ.get("ROS_DOMAIN_ID", str(1 + os.getpid() % 100)),
    }


@dataclass
class Measurement:
    """One repeat of one row in one mode."""

    sent: int
    received: int
    rate: float = math.nan
    offered: float = math.nan
    p50: float = math.nan
    p99: float = math.nan
    max: float = math.nan


def measure(link: Link, case: Case, mode: Mode, settings: Settings, run_id: int) -> Measurement:
    """One repeat of ``case`` in fresh processes (a fresh server for bridge rows)."""
    count = (settings.count + WARMUP) if mode == "latency" else 10**9
    params: Params = {"topic": f"/rlbridge_bench_{os.getpid()}_{run_id}", "mode": mode,
                      "rate_hz": settings.rate_hz, "count": count,
                      "seconds": settings.seconds, "idle_s": settings.idle_s,
                      "transport": case.transport,
                      "reliability": "best_effort" if case.transport == "udp" and case.source
                      == "sdk" else "reliable"}
    timeout = (count / settings.rate_hz if mode == "latency" else settings.seconds) + 60.0
    with ProcessGroup(link, lifetime_s=timeout + 120.0) as group:
        try:
            measured = []
            if "sdk" in (case.source, case.sink):
                server, host, port = start_server(group, adapter="ros2", nodelay=True,
                                                  node_name=f"rlbridge_bench_{run_id}")
                params.update(host=host, port=port)
                measured.append(server)
            rx = group.start("receiver", "a", MODULE, f"{case.sink}_subscriber", params)
            tx = group.start("sender", "b", MODULE, f"{case.source}_publisher", params)
            for worker in (rx, tx):
                worker.expect("ready", STARTUP_S)
            flow = run_flow(tx, rx, [tx, rx, *measured], timeout)
        except BenchError as exc:
            raise BenchError(f"{exc}{group.diagnostics()}") from None
    sent, received = int(flow.sent["sent"]), int(flow.received["received"])
    if mode == "throughput":
        span = float(flow.sent["t_end"]) - float(flow.sent["t_start"])
        return Measurement(sent, received, rate=flow.rate,
                           offered=sent / span if span > 0 else math.nan)
    kept = sorted(s / 1000.0 for s in flow.received["samples"][WARMUP:])
    return Measurement(sent, received, p50=percentile(kept, 50), p99=percentile(kept, 99),
                       max=kept[-1] if kept else math.nan)


# -- runs and report -----------------------------------------------------------------------
@dataclass(frozen=True)
class Settings:
    """What ``rlbridge bench ros2`` was asked for (also printed in the report)."""

    rate_hz: float = 1000.0
    count: int = 3000
    seconds: float = 2.0
    repeats: int = 3
    idle_s: float = 0.5
    modes: tuple[Mode, ...] = ("latency", "throughput")
    only: tuple[str, ...] = ()


@dataclass
class CaseResult:
    case: Case
    mode: Mode
    runs: list[Measurement] = field(default_factory=list)

    def stat(self, name: str) -> float:
        return median([float(getattr(m, name)) for m in self.runs])

    def lost(self) -> float:
        return median([float(m.sent - m.received) for m in self.runs])

    def lost_percent(self) -> str:
        share = median([100.0 * (m.sent - m.received) / m.sent if m.sent else math.nan
                        for m in self.runs])
        return "-" if math.isnan(share) else f"{share:.1f} %"


def run(link: Link, settings: Settings,
        progress: Callable[[str], None] | None = None) -> list[CaseResult]:
    """Every (row, mode) ``repeats`` times, interleaved; discovery scoped for every process."""
    selected: list[Case] = select_cases(CASES, settings.only)
    scoped = RosScopedLink(link, ros_scope())
    results = [CaseResult(c, m) for m in settings.modes for c in selected]
    run_id = 0
    for rep in range(settings.repeats):
        for res in results:
            if progress is not None:
                progress(f"ros2 {res.mode} {rep + 1}/{settings.repeats}: {res.case.label}")
            run_id += 1
            try:
                res.runs.append(measure(scoped, res.case, res.mode, settings, run_id))
            except BenchError as exc:
                raise BenchError(f"{res.case.label} ({res.mode}): {exc}") from None
    return results


def _baseline(results: Sequence[CaseResult], mode: Mode) -> CaseResult | None:
    return next((r for r in results if r.mode == mode and r.case.key == "rclpy" and r.runs),
                None)


def table(results: Sequence[CaseResult], mode: Mode) -> str:
    """Medians over repeats, and each row's ratio to rclpy node -> node of the same run."""
    base = _baseline(results, mode)
    rows = []
    for r in (x for x in results if x.mode == mode):
        if mode == "throughput":
            rows.append([r.case.label, fmt(r.stat("offered")), fmt(r.stat("rate")),
                         fmt(ratio(r.stat("rate"), base.stat("rate") if base else math.nan), 2),
                         fmt(r.stat("received")), r.lost_percent()])
        else:
            rows.append([r.case.label] + [fmt(r.stat(k), 1) for k in ("p50", "p99", "max")]
                        + [fmt(ratio(r.stat(k), base.stat(k) if base else math.nan), 2)
                           for k in ("p50", "p99")] + [fmt(r.lost())])
    headers = (["path", "sent/s", "received values/s", "x rclpy node -> node",
                "received/run", "lost"]
               if mode == "throughput" else
               ["path", "p50 us", "p99 us", "max us", "p50 x rclpy", "p99 x rclpy", "lost/run"])
    return markdown_table(headers, rows)


def report(results: Sequence[CaseResult], settings: Settings, command: Sequence[str]) -> str:
    """The markdown section ``rlbridge bench ros2 --out`` writes."""
    scope = ros_scope()
    parts = [
        report_header("ROS 2 adapter", command),
        f"{settings.repeats} repeats per row, interleaved; medians over repeats. Float64, "
        f"KEEP_LAST({DEPTH}); discovery {scope['ROS_AUTOMATIC_DISCOVERY_RANGE']}. "
        "Bridge rows: 3 processes, 2 hops (rclpy node, `rlbridge serve --adapter ros2 "
        "--nodelay`, SDK with `nodelay=True`); the baseline: 2 rclpy processes, 1 hop. "
        "Throughput: *sent/s* is what the sender managed to offer, *received values/s* what "
        "arrived (a KEEP_LAST(10) reader that falls behind loses the oldest values; every loss "
        "is in *lost*).",
    ]
    if "latency" in settings.modes:
        parts += ["", f"Latency, {settings.rate_hz:g} Hz stream, {settings.count:,} samples per "
                  f"run after {WARMUP} warm-up samples (sender's `time.time_ns()` -> receiver's "
                  "callback or blocking read):", "", table(results, "latency")]
    if "throughput" in settings.modes:
        parts += ["", f"Throughput, flood for {settings.seconds:g} s per run (values received / "
                  "(last arrival - first send)):", "", table(results, "throughput")]
    return "\n".join(parts) + "\n"


def parse_modes(text: str) -> tuple[Mode, ...]:
    """``"latency,throughput"`` -> the modes; anything else is a one-line error."""
    modes = tuple(m.strip() for m in text.split(",") if m.strip())
    bad = [m for m in modes if m not in ("latency", "throughput")]
    if bad or not modes:
        raise BenchError(f"--modes takes latency and/or throughput, not {text!r}")
    return modes  # type: ignore[return-value]


def bench(link: Link, settings: Settings, command: Sequence[str],
          progress: Callable[[str], None] | None = None) -> str:
    """Run and report: what ``rlbridge bench ros2`` does."""
    return report(run(link, settings, progress), settings, command)
