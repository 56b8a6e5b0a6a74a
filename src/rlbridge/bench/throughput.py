"""``rlbridge bench throughput``: values per second through the bridge, next to baselines.

The rlbridge path is the deployed one, three processes and two hops: an SDK publisher writes
``std_msgs/msg/Float64`` values into an outgoing channel; the bridge server (the in-process bus
as its middleware) hands them to the subscription of a second client; that SDK subscriber reads
them from a blocking incoming channel. The baselines (raw UDP, ZeroMQ, Zenoh) are one hop, two
processes, 8-byte messages, from the same run.

Two shapes of traffic:

* ``batch == 1``, one value per packet: the publisher calls ``write`` per value and the server
  runs with ``max_batch=1``, so every packet on both hops (TCP frame or UDP datagram) carries
  exactly one value. Compared with the raw UDP loop's datagrams per second.
* ``batch > 1``: the publisher calls ``write_many`` with ``batch`` values; the SDK and the
  server move them as Batch packets (a UDP datagram holds what fits in 1400 bytes).

The publisher is flow-controlled by its own ring: it waits while more than half of the
channel's buffer is still unsent, so what is measured is what the path can carry, not how fast
a loop can overwrite a buffer. UDP can still lose datagrams at either hop under overload; every
loss is counted (server-side sequence gaps for the first hop, ``IncomingChannel.lost`` for the
second, ring overwrites at either end) and reported next to the rate.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from rlbridge.bench import baselines
from rlbridge.bench.common import (
    BenchError,
    Control,
    Flow,
    Link,
    Params,
    ProcessGroup,
    Role,
    Skipped,
    Tally,
    emit,
    fmt,
    markdown_table,
    median,
    ratio,
    run_flow,
    start_server,
    wait_for_go,
)

MODULE = "rlbridge.bench.throughput"
TOPIC = "/bench/throughput"
MSG_TYPE = "std_msgs/msg/Float64"
SUB_BUFFER = 1 << 18


@dataclass(frozen=True)
class Case:
    """One row: ``kind`` is ``rlbridge`` or a baseline (``udp``, ``zmq``, ``zenoh``)."""

    label: str
    kind: str
    transport: str = "udp"
    batch: int = 1


CASES = (
    Case("raw UDP socket, 1 hop", "udp"),
    Case("ZeroMQ PUB/SUB tcp, 1 hop", "zmq"),
    Case("Zenoh peer tcp, 1 hop", "zenoh"),
    Case("rlbridge UDP, 1 value/datagram", "rlbridge", "udp", 1),
    Case("rlbridge TCP, 1 value/frame", "rlbridge", "tcp", 1),
    Case("rlbridge UDP, write_many(4096)", "rlbridge", "udp", 4096),
    Case("rlbridge TCP, write_many(4096)", "rlbridge", "tcp", 4096),
)


# -- worker roles (child processes) --------------------------------------------------------
def publisher(params: Params) -> None:
    """SDK publisher: ``write`` per value (batch 1) or ``write_many`` of ``batch`` values."""
    from rlbridge.csp.bridge import Bridge

    control = Control()
    batch = int(params["batch"])
    buffer = max(4 * batch, 1 << 16)
    bridge = Bridge.connect(params["host"], int(params["port"]), name="bench-pub")
    out = bridge.publish(TOPIC, MSG_TYPE, "data", transport=params["transport"],
                         buffer_size=buffer)
    values = [float(i) for i in range(batch)]
    high = buffer // 2
    count, seconds = int(params["count"]), float(params["seconds"])
    emit("ready")
    wait_for_go(control)
    sent = 0
    start = time.monotonic()
    end = start + seconds
    rate = float(params.get("rate", 0.0))
    while sent < count and time.monotonic() < end:
        while out.pending() > high:
            time.sleep(0.0001)
        if rate > 0:  # offered load: stay on the schedule, at most 1 ms ahead
            delay = start + sent / rate - time.monotonic()
            if delay > 0.001:
                time.sleep(delay - 0.001)
        if batch == 1:
            write = out.write
            n = min(256, count - sent)
            for v in range(n):
                write(float(v))
        else:
            n = min(batch, count - sent)
            out.write_many(values if n == batch else values[:n])
        sent += n
    bridge.send(wait=True)
    stats = out.statistics()
    emit("sent", sent=sent, t_start=start, t_end=time.monotonic(), written=stats.written,
         overwritten=stats.overwritten, taken=stats.read)
    control.wait("stats", 120.0)
    channel = bridge.server_stats()["session"]["channels"][str(out.channel_id)]
    emit("stats", values_in=channel["values_in"], lost=channel["lost"],
         bad_values=channel["bad_values"])
    control.wait("never", 1e9)


def subscriber(params: Params) -> None:
    """SDK subscriber: blocking ``read`` then ``read_many`` of everything else waiting."""
    from rlbridge.csp.bridge import Bridge

    control = Control()
    bridge = Bridge.connect(params["host"], int(params["port"]), name="bench-sub")
    ch = bridge.subscribe(TOPIC, MSG_TYPE, "data", transport=params["transport"],
                          blocking=True, buffer_size=SUB_BUFFER)
    emit("ready")
    emit("joined")
    tally = Tally(control, float(params["idle_s"]))
    read, read_many, mono = ch.read, ch.read_many, time.monotonic
    while not tally.done(mono()):
        try:
            read(0.05)
        except TimeoutError:
            continue
        tally.add(1 + len(read_many()), mono())
    stats = ch.statistics()
    server = bridge.server_stats()["session"]["channels"]
    out = next(iter(server.values()))
    tally.report(lost=ch.lost, duplicates=ch.duplicates, overwritten=stats.overwritten,
                 arrived=stats.written, values_out=out["values_out"], dropped=out["dropped"])
    control.wait("never", 1e9)


ROLES: dict[str, Role] = {"publisher": publisher, "subscriber": subscriber}


# -- one measurement (parent) --------------------------------------------------------------
@dataclass
class Measurement:
    """One repeat of one case: rate, CPU per million values by process, losses by stage."""

    rate: float
    cpu: dict[str, float]
    loss: dict[str, int] = field(default_factory=dict)


def _rlbridge_once(group: ProcessGroup, case: Case, count: int, seconds: float,
                   idle_s: float, timeout: float, rate: float) -> Measurement:
    server, host, port = start_server(group, max_batch=case.batch)
    common: Params = {"host": host, "port": port, "transport": case.transport}
    sub, _ = group.spawn("subscriber", "b", MODULE, "subscriber", {**common, "idle_s": idle_s})
    pub, _ = group.spawn("publisher", "b", MODULE, "publisher",
                         {**common, "batch": case.batch, "count": count, "seconds": seconds,
                          "rate": rate})
    flow = run_flow(pub, sub, [pub, server, sub], timeout, expect_key="taken")
    pub.send("stats")
    hop1 = pub.expect("stats", 30.0)
    got = flow.received
    taken = int(flow.sent["taken"])
    loss = {
        "publisher ring": int(flow.sent["overwritten"]),
        "hop 1 (publisher -> server)": taken - int(hop1["values_in"]),
        "hop 1 gaps": int(hop1["lost"]),
        "server drops": int(got["dropped"]),
        "hop 2 (server -> subscriber)": int(got["values_out"]) - int(got["dropped"])
        - int(got["arrived"]) - int(got["duplicates"]),
        "hop 2 gaps (IncomingChannel.lost)": int(got["lost"]),
        "subscriber ring": int(got["overwritten"]),
        "end to end": int(flow.sent["written"]) - int(got["received"]),
    }
    return _measurement(flow, loss)


def _baseline_once(group: ProcessGroup, case: Case, count: int, seconds: float,
                   idle_s: float, timeout: float, rate: float) -> Measurement:
    tx, rx = baselines.spawn_pair(group, case.kind, {"mode": "flood", "count": count,
                                                     "seconds": seconds, "idle_s": idle_s})
    flow = run_flow(tx, rx, [tx, rx], timeout)
    return _measurement(flow, {"end to end": int(flow.sent["sent"])
                               - int(flow.received["received"])})


def _measurement(flow: Flow, loss: dict[str, int]) -> Measurement:
    cpu = {name: flow.cpu_per_million(name) for name in flow.cpu_s}
    cpu["total"] = sum(cpu.values())
    return Measurement(flow.rate, cpu, loss)


def measure(link: Link, case: Case, *, count: int, seconds: float, idle_s: float = 0.5,
            timeout: float = 120.0, rate: float = 0.0) -> Measurement:
    """One repeat of ``case`` over ``link``, in fresh processes that are all gone after it."""
    once = _rlbridge_once if case.kind == "rlbridge" else _baseline_once
    with ProcessGroup(link, lifetime_s=seconds + timeout + 60) as group:
        try:
            return once(group, case, count, seconds, idle_s, timeout, rate)
        except BenchError as exc:
            raise BenchError(f"{exc}{group.diagnostics()}") from None


# -- report --------------------------------------------------------------------------------
@dataclass
class CaseResult:
    case: Case
    runs: list[Measurement] = field(default_factory=list)
    skipped: str | None = None

    @property
    def rate(self) -> float:
        return median([m.rate for m in self.runs])

    def cpu(self, name: str) -> float:
        return median([m.cpu.get(name, math.nan) for m in self.runs])


def run(link: Link, cases: Sequence[Case], *, count: int, seconds: float, repeats: int,
        idle_s: float = 0.5, progress: Any = None) -> list[CaseResult]:
    """Every case ``repeats`` times, interleaved so that a noisy minute hits every row."""
    results = [CaseResult(c) for c in cases]
    for rep in range(repeats):
        for res in results:
            if res.skipped is not None:
                continue
            if progress is not None:
                progress(f"repeat {rep + 1}/{repeats}: {res.case.label}")
            try:
                res.runs.append(measure(link, res.case, count=count, seconds=seconds,
                                        idle_s=idle_s))
            except Skipped as exc:
                res.skipped = str(exc)
            except BenchError as exc:
                raise BenchError(f"{res.case.label}: {exc}") from None
    return results


def table(results: Sequence[CaseResult]) -> str:
    base = {r.case.kind: r.rate for r in results if r.case.kind != "rlbridge"}
    headers = ["path", "values/s (median)", "x raw UDP", "x ZeroMQ", "x Zenoh",
               "CPU s/M values: sender/pub", "server", "receiver/sub", "total",
               "lost end to end (median)"]
    rows = []
    for r in results:
        if r.skipped is not None:
            rows.append([r.case.label, f"skipped: {r.skipped}"] + [""] * (len(headers) - 2))
            continue
        sender = r.cpu("publisher") if r.case.kind == "rlbridge" else r.cpu("sender")
        receiver = r.cpu("subscriber") if r.case.kind == "rlbridge" else r.cpu("receiver")
        lost = median([float(m.loss.get("end to end", 0)) for m in r.runs])
        rows.append([r.case.label, fmt(r.rate), fmt(ratio(r.rate, base.get("udp", math.nan)), 2),
                     fmt(ratio(r.rate, base.get("zmq", math.nan)), 2),
                     fmt(ratio(r.rate, base.get("zenoh", math.nan)), 2), fmt(sender, 2),
                     fmt(r.cpu("server"), 2), fmt(receiver, 2), fmt(r.cpu("total"), 2),
                     fmt(lost)])
    return markdown_table(headers, rows)


def loss_table(results: Sequence[CaseResult]) -> str:
    """Where values were lost, per rlbridge case and repeat (UDP overload shows up here)."""
    rows = []
    for r in results:
        if r.case.kind != "rlbridge":
            continue
        for i, m in enumerate(r.runs):
            stages = ", ".join(f"{k}: {v:,}" for k, v in m.loss.items() if v)
            rows.append([r.case.label, str(i + 1), fmt(m.rate), stages or "none"])
    return markdown_table(["path", "repeat", "values/s", "losses by stage"], rows)
