"""``rlbridge bench feedback``: how soon a UDP flood's first-hop loss reaches its publisher.

A publisher process floods a UDP channel (``write_many`` of 4096 ``Float64`` values whenever
less than half its ring waits) through a bridge server process, for a fixed time. Between
writes it reads ``channel.health()`` and notes when the first loss report showing loss
arrived; the figure is that moment minus the start of the flood (an upper bound on the time
from the first lost datagram to the publisher knowing: the loss itself starts later). The
server's heartbeat period (the report period) is printed next to it, same run.

Rows: the flood without a limit, and with ``max_rate_hz`` + ``adapt_rate`` (AIMD on the
reports), so the table also shows what adapting to the reports saves. At the end the
publisher's reported counts are compared with the server's own (they must match once the
last report is in).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from rlbridge.bench.common import (
    BenchError,
    Control,
    Link,
    Params,
    ProcessGroup,
    Role,
    emit,
    fmt,
    hold,
    markdown_table,
    median,
    report_header,
    select_cases,
    start_server,
    wait_for_go,
)
from rlbridge.csp.options import Policy

MODULE = "rlbridge.bench.feedback"
TOPIC = "/bench/flood"
MSG_TYPE = "std_msgs/msg/Float64"
BATCH = 4096
TARGET_S = 1.0
HEARTBEAT_MS = 200  # the server's default: one loss report per period at most


@dataclass(frozen=True)
class Case:
    key: str
    label: str
    #: ``max_rate_hz`` with ``adapt_rate`` (0: no limit).
    adapt_from: float = 0.0


CASES = (
    Case("flood", "UDP flood, no limit"),
    Case("flood-adapt", "UDP flood, max_rate_hz=20,000,000, adapt_rate", 20_000_000.0),
)


def publisher(params: Params) -> None:
    """Flood for ``seconds``; note when health() first shows loss; report counts."""
    from rlbridge.csp.bridge import Bridge

    control = Control()
    bridge = Bridge.connect(params["host"], int(params["port"]), name="bench-flood")
    adapt = float(params["adapt_from"])
    buffer = 4 * BATCH
    out = bridge.publish(TOPIC, MSG_TYPE, "data", transport="udp", buffer_size=buffer,
                         policy=Policy(max_rate_hz=adapt or None, adapt_rate=bool(adapt)))
    values = [float(i) for i in range(BATCH)]
    emit("ready")
    wait_for_go(control)
    start = time.monotonic()
    end = start + float(params["seconds"])
    first_loss = math.nan
    written = 0
    while time.monotonic() < end:
        if out.pending() < buffer // 2:
            out.write_many(values)
            written += BATCH
        else:
            time.sleep(0.0002)
        if math.isnan(first_loss) and out.health().lost > 0:
            first_loss = time.monotonic() - start
    bridge.send(wait=True)
    # The server may still be draining its receive buffer: compare once both sides agree,
    # or after 10 s (then the row says they did not).
    settle = time.monotonic() + 10.0
    while True:
        time.sleep(HEARTBEAT_MS / 1000)
        server = bridge.server_stats()["session"]["channels"][str(out.channel_id)]
        time.sleep(2 * HEARTBEAT_MS / 1000)  # a report with those counts comes in
        health = out.health()
        if (health.lost, health.arrived) == (server["lost"], server["values_in"]) \
                or time.monotonic() > settle:
            break
    emit("sent", written=written, taken=out.statistics().read, first_loss_s=first_loss,
         reported_lost=health.lost, reported_arrived=health.arrived,
         server_lost=server["lost"], server_in=server["values_in"],
         rate_limit_hz=health.rate_limit_hz)
    hold(control)


ROLES: dict[str, Role] = {"publisher": publisher}


@dataclass
class Run:
    first_loss_s: float
    taken: int
    reported_lost: int
    server_lost: int
    matches: bool
    rate_limit_hz: int


@dataclass
class CaseResult:
    case: Case
    runs: list[Run] = field(default_factory=list)


def measure(link: Link, case: Case, seconds: float) -> Run:
    """One flood in fresh processes (server and publisher)."""
    with ProcessGroup(link, lifetime_s=seconds + 120) as group:
        try:
            # The receive buffer these figures were first measured with (the server's default
            # is 32 MiB now, docs/load.md): a larger one only delays the flood's first loss.
            _server, host, port = start_server(group, heartbeat_ms=HEARTBEAT_MS,
                                               udp_receive_buffer=4 << 20)
            pub = group.start("publisher", "b", MODULE, "publisher", {
                "host": host, "port": port, "seconds": seconds, "adapt_from": case.adapt_from})
            pub.expect("ready", 30.0)
            pub.send("go")
            got = pub.expect("sent", seconds + 60.0)
        except BenchError as exc:
            raise BenchError(f"{exc}{group.diagnostics()}") from None
    return Run(float(got["first_loss_s"]), int(got["taken"]), int(got["reported_lost"]),
               int(got["server_lost"]), int(got["reported_lost"]) == int(got["server_lost"])
               and int(got["reported_arrived"]) == int(got["server_in"]),
               int(got["rate_limit_hz"]))


def run(link: Link, repeats: int, seconds: float, only: Sequence[str] = (),
        progress: Callable[[str], None] | None = None) -> list[CaseResult]:
    """Every case ``repeats`` times, interleaved."""
    results = [CaseResult(c) for c in select_cases(CASES, only)]
    for rep in range(repeats):
        for res in results:
            if progress is not None:
                progress(f"feedback {rep + 1}/{repeats}: {res.case.label}")
            res.runs.append(measure(link, res.case, seconds))
    return results


def report(results: Sequence[CaseResult], repeats: int, seconds: float,
           command: Sequence[str]) -> str:
    """The markdown section ``rlbridge bench feedback --out`` writes."""
    rows, lines = [], []
    for r in results:
        times = [x.first_loss_s for x in r.runs]
        seen = [t for t in times if not math.isnan(t)]
        lost = median([x.server_lost / x.taken if x.taken else math.nan for x in r.runs])
        rows.append([r.case.label, fmt(1000 * median(seen), 0) if seen else "never",
                     fmt(1000 * max(seen), 0) if seen else "never", f"{HEARTBEAT_MS}",
                     f"{100 * lost:.1f} %", f"{sum(x.matches for x in r.runs)}/{len(r.runs)}",
                     fmt(median([float(x.rate_limit_hz) for x in r.runs]))
                     if r.case.adapt_from else "-"])
        if not any(x.server_lost for x in r.runs):
            lines.append(f"- {r.case.label}: nothing lost at hop 1, nothing to report")
            continue
        ok = len(seen) == len(times) and bool(seen) and max(seen) <= TARGET_S
        verdict = "met" if ok else "not met"
        lines.append(f"- {r.case.label}: loss visible to the publisher after at most "
                     f"{fmt(1000 * max(seen), 0) if seen else 'never'} ms (from the flood's "
                     f"start); target <= {TARGET_S * 1000:.0f} ms: **{verdict}**")
    table = markdown_table(
        ["flood", "loss visible after, median ms", "max ms", "report period ms",
         "lost at hop 1 (server's count)", "reported = server's count", "rate limit at end"],
        rows)
    return "\n".join([
        report_header("Loss feedback", command),
        f"{repeats} repeats per row, interleaved; each a {seconds:g} s flood of "
        f"`write_many({BATCH})` on a UDP channel through a server process (loopback). "
        "`loss visible after` = time from the flood's start until `channel.health().lost` "
        "first showed loss in the publisher (an upper bound on loss-to-knowledge). "
        "`reported = server's count`: runs where the publisher's reported counts equalled the "
        "server's own after the flood (within 10 s).",
        "", table, "", "Targets:", "", *lines]) + "\n"
