"""``rlbridge bench latency``: one-way latency of a periodic stream, next to baselines.

A publisher process writes ``time.time_ns()`` as a ``std_msgs/msg/Int64`` value at a fixed rate
(1 kHz and 100 Hz: a control loop's set-points and a slower status stream); the subscriber
process reads it from a *blocking* channel and records ``time.time_ns() - value`` the moment the
value is readable. Both processes run on one machine, so they share the clock and the figure is
one-way latency, not half a round trip. The rlbridge path is SDK publisher -> server -> SDK
subscriber (two hops, three processes) over TCP with Nagle's algorithm, TCP with ``nodelay`` on
both ends, and UDP; the baselines are one hop: a raw UDP socket pair (the floor) and ZeroMQ
PUB/SUB over TCP (what a user would otherwise pick).

Where the processes run is the :class:`~rlbridge.bench.common.Link`'s business: the server and
baseline receivers on side ``"a"``, publishers and senders on side ``"b"``, so an emulated link
with delay and loss can be put between the sides without touching this module. Each run
discards its first ``WARMUP`` samples (connection set-up, first-touch allocation).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from rlbridge.bench import baselines
from rlbridge.bench.common import (
    BenchError,
    Control,
    Link,
    Params,
    ProcessGroup,
    Role,
    Skipped,
    Tally,
    emit,
    fmt,
    hold,
    markdown_table,
    median,
    paced,
    percentile,
    ratio,
    run_flow,
    start_server,
    wait_for_go,
)

MODULE = "rlbridge.bench.latency"
TOPIC = "/bench/latency"
MSG_TYPE = "std_msgs/msg/Int64"
WARMUP = 20


@dataclass(frozen=True)
class Case:
    """One row: ``kind`` is ``rlbridge`` or a baseline (``udp``, ``zmq``)."""

    label: str
    kind: str
    transport: str = "udp"
    nodelay: bool = False


CASES = (
    Case("raw UDP socket, 1 hop", "udp"),
    Case("ZeroMQ PUB/SUB tcp, 1 hop", "zmq"),
    Case("rlbridge UDP", "rlbridge", "udp"),
    Case("rlbridge TCP, nodelay", "rlbridge", "tcp", nodelay=True),
    Case("rlbridge TCP, Nagle", "rlbridge", "tcp", nodelay=False),
)
RATES = (1000.0, 100.0)


# -- worker roles (child processes) --------------------------------------------------------
def publisher(params: Params) -> None:
    """Writes ``time.time_ns()`` on schedule; ``write`` hands it to the SDK's send thread."""
    from rlbridge.csp.bridge import Bridge

    control = Control()
    bridge = Bridge.connect(params["host"], int(params["port"]), nodelay=bool(params["nodelay"]),
                            name="bench-lat-pub")
    out = bridge.publish(TOPIC, MSG_TYPE, "data", transport=params["transport"])
    emit("ready")
    wait_for_go(control)
    sent, t0, t1 = paced(out.write, float(params["rate_hz"]), int(params["count"]))
    emit("sent", sent=sent, t_start=t0, t_end=t1)
    hold(control)


def subscriber(params: Params) -> None:
    """Blocking reads; the latency of a value is taken as soon as ``read`` returns it."""
    from rlbridge.csp.bridge import Bridge

    control = Control()
    bridge = Bridge.connect(params["host"], int(params["port"]), nodelay=bool(params["nodelay"]),
                            name="bench-lat-sub")
    ch = bridge.subscribe(TOPIC, MSG_TYPE, "data", transport=params["transport"],
                          blocking=True, buffer_size=1024)
    emit("ready")
    emit("joined")
    tally = Tally(control, float(params["idle_s"]))
    samples, read, now_ns, mono = tally.samples, ch.read, time.time_ns, time.monotonic
    while not tally.done(mono()):
        try:
            value = read(0.05)
        except TimeoutError:
            continue
        samples.append(now_ns() - value)
        tally.add(1, mono())
    tally.report(lost=ch.lost, overwritten=ch.statistics().overwritten)


ROLES: dict[str, Role] = {"publisher": publisher, "subscriber": subscriber}


# -- one measurement (parent) --------------------------------------------------------------
@dataclass
class Measurement:
    """One repeat: latency percentiles in microseconds, samples kept, values lost."""

    p50: float
    p99: float
    max: float
    samples: int
    lost: int


def _summary(samples_ns: Sequence[int], sent: int) -> Measurement:
    kept = sorted(s / 1000.0 for s in samples_ns[WARMUP:])
    return Measurement(percentile(kept, 50), percentile(kept, 99),
                       kept[-1] if kept else math.nan, len(kept), sent - len(samples_ns))


def _rlbridge_once(group: ProcessGroup, case: Case, stream: Params) -> Measurement:
    server, host, port = start_server(group, nodelay=case.nodelay)
    common: Params = {"host": host, "port": port, "transport": case.transport,
                      "nodelay": case.nodelay, **stream}
    sub, _ = group.spawn("subscriber", "b", MODULE, "subscriber", common)
    pub, _ = group.spawn("publisher", "b", MODULE, "publisher", common)
    flow = run_flow(pub, sub, [pub, server, sub], _timeout(stream))
    return _summary(flow.received["samples"], int(flow.sent["sent"]))


def _timeout(stream: Params) -> float:
    return float(stream["count"]) / float(stream["rate_hz"]) + 30.0


def measure(link: Link, case: Case, *, rate_hz: float, count: int,
            idle_s: float = 0.5) -> Measurement:
    """One repeat of ``case`` at ``rate_hz`` over ``link``, in fresh processes."""
    stream: Params = {"rate_hz": rate_hz, "count": count, "idle_s": idle_s}
    with ProcessGroup(link, lifetime_s=_timeout(stream) + 120) as group:
        try:
            if case.kind == "rlbridge":
                return _rlbridge_once(group, case, stream)
            tx, rx = baselines.spawn_pair(group, case.kind, {"mode": "paced", **stream})
            flow = run_flow(tx, rx, [tx, rx], _timeout(stream))
            return _summary(flow.received["samples"], int(flow.sent["sent"]))
        except BenchError as exc:
            raise BenchError(f"{exc}{group.diagnostics()}") from None


# -- report --------------------------------------------------------------------------------
@dataclass
class CaseResult:
    case: Case
    rate_hz: float
    runs: list[Measurement] = field(default_factory=list)
    skipped: str | None = None

    def stat(self, name: str) -> float:
        return median([float(getattr(m, name)) for m in self.runs])


def run(link: Link, cases: Sequence[Case], rates: Sequence[float], *, seconds: float,
        count: int | None, repeats: int,
        progress: Callable[[str], None] | None = None) -> list[CaseResult]:
    """Every (case, rate) ``repeats`` times, interleaved so that noise hits every row."""
    results = [CaseResult(c, r) for r in rates for c in cases]
    for rep in range(repeats):
        for res in results:
            if res.skipped is not None:
                continue
            if progress is not None:
                progress(f"repeat {rep + 1}/{repeats}: {res.case.label} at {res.rate_hz:g} Hz")
            n = count if count is not None else max(WARMUP + 10, int(seconds * res.rate_hz))
            try:
                res.runs.append(measure(link, res.case, rate_hz=res.rate_hz, count=n + WARMUP))
            except Skipped as exc:
                res.skipped = str(exc)
            except BenchError as exc:
                raise BenchError(f"{res.case.label} at {res.rate_hz:g} Hz: {exc}") from None
    return results


def table(results: Sequence[CaseResult]) -> str:
    """p50/p99/max medians over repeats, and the targets' ratios (per stream rate)."""
    headers = ["stream", "path", "p50 us", "p99 us", "max us", "p50 / raw UDP p50",
               "p99 / ZeroMQ p99", "samples/run", "lost (median)"]
    rows = []
    for r in results:
        if r.skipped is not None:
            rows.append([f"{r.rate_hz:g} Hz", r.case.label, f"skipped: {r.skipped}"]
                        + [""] * (len(headers) - 3))
            continue
        peers = {x.case.kind: x for x in results if x.rate_hz == r.rate_hz and x.runs}
        udp, zmq = peers.get("udp"), peers.get("zmq")
        rows.append([
            f"{r.rate_hz:g} Hz", r.case.label, fmt(r.stat("p50"), 1), fmt(r.stat("p99"), 1),
            fmt(r.stat("max"), 1),
            fmt(ratio(r.stat("p50"), udp.stat("p50") if udp else math.nan), 2),
            fmt(ratio(r.stat("p99"), zmq.stat("p99") if zmq else math.nan), 2),
            fmt(r.stat("samples")), fmt(r.stat("lost")),
        ])
    return markdown_table(headers, rows)
