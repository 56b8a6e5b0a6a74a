"""``rlbridge bench latency``: one-way latency of a periodic stream, next to baselines.

A publisher process writes ``time.time_ns()`` as a ``std_msgs/msg/Int64`` value at a fixed rate
(1 kHz and 100 Hz: a control loop's set-points and a slower status stream); the subscriber
process reads it from a *blocking* channel and records ``time.time_ns() - value`` the moment the
value is readable. Both processes run on one machine, so they share the clock and the figure is
one-way latency, not half a round trip. The rlbridge path is SDK publisher -> server -> SDK
subscriber (two hops, three processes) over TCP with Nagle's algorithm, TCP with ``nodelay`` on
both ends, and UDP; the baselines are one hop: a raw UDP socket pair (the floor) and ZeroMQ
PUB/SUB over TCP (what a user would otherwise pick).

``--idle park,spin,busy`` adds the rlbridge rows once per SDK idle strategy
(:mod:`rlbridge.csp.idle`, in the publisher and the subscriber; ``park/spin`` gives the send
thread the first and the receive thread the second), with the CPU each process used
(% of one core over the run) and the publisher loop's own wake-up lateness p99: a spinning SDK
thread holds the GIL the loop needs when it wakes, and this column shows what that costs.

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
    report_header,
    rlbridge_flow,
    run_flow,
    select_cases,
    wait_for_go,
)
from rlbridge.cli.options import tuning_of

MODULE = "rlbridge.bench.latency"
TOPIC = "/bench/latency"
MSG_TYPE = "std_msgs/msg/Int64"
WARMUP = 20


@dataclass(frozen=True)
class Case:
    """One row: ``kind`` is ``rlbridge`` or a baseline (``udp``, ``zmq``)."""

    key: str
    label: str
    kind: str
    transport: str = "udp"
    nodelay: bool = False
    idle: str = "park"
    #: The publisher writes a buffered channel and calls ``bridge.send(inline=True)``.
    inline: bool = False


#: The floor every row is compared with (``latency --stages`` runs it too).
RAW_UDP = Case("udp", "raw UDP socket, 1 hop", "udp")
CASES = (
    RAW_UDP,
    Case("zmq", "ZeroMQ PUB/SUB tcp, 1 hop", "zmq"),
    Case("rlb-udp", "rlbridge UDP", "rlbridge", "udp"),
    Case("rlb-udp-inline", "rlbridge UDP, send(inline=True)", "rlbridge", "udp", inline=True),
    Case("rlb-tcp-nodelay", "rlbridge TCP, nodelay", "rlbridge", "tcp", nodelay=True),
    Case("rlb-tcp-nagle", "rlbridge TCP, Nagle", "rlbridge", "tcp", nodelay=False),
)


# -- worker roles (child processes) --------------------------------------------------------
def with_idle(cases: Sequence[Case], strategies: Sequence[str]) -> tuple[Case, ...]:
    """The rows once per idle strategy: baselines once, rlbridge rows per strategy."""
    rows = [c for c in cases if c.kind != "rlbridge"]
    for idle in strategies:
        rows += [Case(c.key if idle == "park" else f"{c.key}-{idle}",
                      c.label if idle == "park" else f"{c.label}, idle={idle}",
                      c.kind, c.transport, c.nodelay, idle, c.inline)
                 for c in cases if c.kind == "rlbridge"]
    return tuple(rows)


def paced_late(send: Callable[[int], object], rate_hz: float,
               count: int) -> tuple[int, float, float, list[int]]:
    """:func:`paced`, also recording each call's lateness behind its schedule (ns)."""
    period_ns = int(1e9 / rate_hz)
    mono = time.monotonic_ns
    start = mono()
    late: list[int] = []
    for i in range(count):
        due = start + i * period_ns
        delay = due - mono()
        if delay > 0:
            time.sleep(delay / 1e9)
        now = mono()
        late.append(now - due)
        send(time.time_ns())
    return count, start / 1e9, mono() / 1e9, late


def publisher(params: Params) -> None:
    """Writes ``time.time_ns()`` on schedule; ``write`` hands it to the SDK's send thread."""
    from rlbridge.client.bridge import Bridge

    control = Control()
    bridge = Bridge.connect(params["host"], int(params["port"]), nodelay=bool(params["nodelay"]),
                            name="bench-lat-pub",
                            tuning=tuning_of(idle=str(params.get("idle", "park"))))
    inline = bool(params.get("inline"))
    out = bridge.publish(TOPIC, MSG_TYPE, "data", transport=params["transport"],
                         through_buffer=inline)
    write: Callable[[int], object] = out.write
    if inline:  # the round in the loop's thread: no hand-off to the send thread
        send = bridge.send

        def write(value: int) -> None:
            out.write(value)
            send(inline=True)
    emit("ready")
    wait_for_go(control)
    if params.get("idle") is None:
        sent, t0, t1 = paced(write, float(params["rate_hz"]), int(params["count"]))
        emit("sent", sent=sent, t_start=t0, t_end=t1)
    else:
        sent, t0, t1, late = paced_late(write, float(params["rate_hz"]),
                                        int(params["count"]))
        kept = sorted(late[WARMUP:])
        emit("sent", sent=sent, t_start=t0, t_end=t1,
             late_p99_us=percentile(kept, 99) / 1000 if kept else math.nan)
    hold(control)


def subscriber(params: Params) -> None:
    """Blocking reads; the latency of a value is taken as soon as ``read`` returns it."""
    from rlbridge.client.bridge import Bridge

    control = Control()
    bridge = Bridge.connect(params["host"], int(params["port"]), nodelay=bool(params["nodelay"]),
                            name="bench-lat-sub",
                            tuning=tuning_of(idle=str(params.get("idle", "park"))))
    ch = bridge.subscribe(TOPIC, MSG_TYPE, "data", transport=params["transport"],
                          blocking=True, buffer_size=1024)
    emit("ready")
    emit("joined")
    tally = Tally(control, float(params["idle_s"]))
    samples, read, now_ns, mono = tally.samples, ch.read, time.time_ns, time.monotonic
    first_leg: list[int] = []  # publisher's write -> server's send (the server stamps values)
    while not tally.done(mono()):
        try:
            value = read(0.05)
        except TimeoutError:
            continue
        samples.append(now_ns() - value)
        first_leg.append(ch.last_stamp_ns - value)
        tally.add(1, mono())
    tally.report(lost=ch.lost, overwritten=ch.statistics().overwritten, first_leg=first_leg)


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
    #: rlbridge only: p50 of publisher write -> server send, and of server send -> read.
    first_leg_p50: float = math.nan
    second_leg_p50: float = math.nan
    #: With ``--idle``: % of one core per process over the run, and the publisher loop's
    #: wake-up lateness p99 (us).
    cpu_pub: float = math.nan
    cpu_server: float = math.nan
    cpu_sub: float = math.nan
    loop_late_p99: float = math.nan


def _summary(received: Params, sent: int) -> Measurement:
    samples_ns: list[int] = received["samples"]
    kept = sorted(s / 1000.0 for s in samples_ns[WARMUP:])
    m = Measurement(percentile(kept, 50), percentile(kept, 99),
                    kept[-1] if kept else math.nan, len(kept), sent - len(samples_ns))
    legs: list[int] | None = received.get("first_leg")
    if legs:
        pairs = list(zip(samples_ns, legs, strict=True))[WARMUP:]
        m.first_leg_p50 = percentile(sorted(x / 1000.0 for _, x in pairs), 50)
        m.second_leg_p50 = percentile(sorted((t - x) / 1000.0 for t, x in pairs), 50)
    return m


def _rlbridge_once(group: ProcessGroup, case: Case, stream: Params) -> Measurement:
    params: Params = {"transport": case.transport, "nodelay": case.nodelay,
                      "inline": case.inline, **stream}
    if stream.get("idle_rows"):
        params["idle"] = case.idle
    flow = rlbridge_flow(group, MODULE, params, _timeout(stream), nodelay=case.nodelay)
    m = _summary(flow.received, int(flow.sent["sent"]))
    span = float(flow.sent["t_end"]) - float(flow.sent["t_start"])
    if span > 0 and stream.get("idle_rows"):
        m.cpu_pub, m.cpu_server, m.cpu_sub = (
            100 * flow.cpu_s[name] / span for name in ("publisher", "server", "subscriber"))
    m.loop_late_p99 = float(flow.sent.get("late_p99_us", math.nan))
    return m


def _timeout(stream: Params) -> float:
    return float(stream["count"]) / float(stream["rate_hz"]) + 30.0


def measure(link: Link, case: Case, *, rate_hz: float, count: int,
            idle_s: float = 0.5, idle_rows: bool = False) -> Measurement:
    """One repeat of ``case`` at ``rate_hz`` over ``link``, in fresh processes."""
    stream: Params = {"rate_hz": rate_hz, "count": count, "idle_s": idle_s,
                      "idle_rows": idle_rows}
    with ProcessGroup(link, lifetime_s=_timeout(stream) + 120) as group:
        try:
            if case.kind == "rlbridge":
                return _rlbridge_once(group, case, stream)
            tx, rx = baselines.spawn_pair(group, case.kind, {"mode": "paced", **stream})
            flow = run_flow(tx, rx, [tx, rx], _timeout(stream))
            return _summary(flow.received, int(flow.sent["sent"]))
        except BenchError as exc:
            raise BenchError(f"{exc}{group.diagnostics()}") from None


# -- runs and report -----------------------------------------------------------------------
@dataclass(frozen=True)
class Settings:
    """What ``rlbridge bench latency`` was asked for (also printed in the report)."""

    seconds: float = 5.0
    count: int | None = None
    repeats: int = 3
    rates: tuple[float, ...] = (1000.0, 100.0)
    idle_s: float = 0.5
    only: tuple[str, ...] = ()
    #: SDK idle strategies to run the rlbridge rows with (``()``: the default, no CPU columns).
    idle: tuple[str, ...] = ()

    def samples(self, rate_hz: float) -> int:
        """Samples kept per run (``count``, else ``seconds`` at the stream's rate)."""
        return self.count if self.count is not None else max(10, int(self.seconds * rate_hz))


@dataclass
class CaseResult:
    case: Case
    rate_hz: float
    runs: list[Measurement] = field(default_factory=list)
    skipped: str | None = None

    def stat(self, name: str) -> float:
        return median([float(getattr(m, name)) for m in self.runs])


def run(link: Link, settings: Settings,
        progress: Callable[[str], None] | None = None) -> list[CaseResult]:
    """Every (case, rate) ``repeats`` times, interleaved so that noise hits every row."""
    selected = select_cases(with_idle(CASES, settings.idle) if settings.idle else CASES,
                            settings.only)
    results = [CaseResult(c, r) for r in settings.rates for c in selected]
    for rep in range(settings.repeats):
        for res in results:
            if res.skipped is not None:
                continue
            if progress is not None:
                progress(f"latency {rep + 1}/{settings.repeats}: {res.case.label} at "
                         f"{res.rate_hz:g} Hz")
            count = settings.samples(res.rate_hz) + WARMUP
            try:
                res.runs.append(measure(link, res.case, rate_hz=res.rate_hz, count=count,
                                        idle_s=settings.idle_s,
                                        idle_rows=bool(settings.idle)))
            except Skipped as exc:
                res.skipped = str(exc)
            except BenchError as exc:
                raise BenchError(f"{res.case.label} at {res.rate_hz:g} Hz: {exc}") from None
    return results


def _peer(results: Sequence[CaseResult], r: CaseResult, kind: str) -> CaseResult | None:
    return next((x for x in results if x.rate_hz == r.rate_hz and x.case.kind == kind
                 and x.runs), None)


def table(results: Sequence[CaseResult]) -> str:
    """p50/p99/max (medians over repeats) and the targets' ratios, per stream rate."""
    headers = ["stream", "path", "p50 us", "p99 us", "max us", "p50 / raw UDP p50",
               "p99 / ZeroMQ p99", "p50 pub -> server send", "p50 server send -> read",
               "samples/run", "lost/run"]
    cpu = any(not math.isnan(m.cpu_pub) for r in results for m in r.runs)
    if cpu:
        headers += ["CPU % pub", "CPU % server", "CPU % sub", "pub loop late p99 us"]
    rows = []
    for r in results:
        if r.skipped is not None:
            rows.append([f"{r.rate_hz:g} Hz", r.case.label, f"skipped: {r.skipped}"]
                        + [""] * (len(headers) - 3))
            continue
        udp, zmq = _peer(results, r, "udp"), _peer(results, r, "zmq")
        rows.append([
            f"{r.rate_hz:g} Hz", r.case.label, fmt(r.stat("p50"), 1), fmt(r.stat("p99"), 1),
            fmt(r.stat("max"), 1),
            fmt(ratio(r.stat("p50"), udp.stat("p50") if udp else math.nan), 2),
            fmt(ratio(r.stat("p99"), zmq.stat("p99") if zmq else math.nan), 2),
            fmt(r.stat("first_leg_p50"), 1), fmt(r.stat("second_leg_p50"), 1),
            fmt(r.stat("samples")), fmt(r.stat("lost")),
            *([fmt(r.stat("cpu_pub"), 1), fmt(r.stat("cpu_server"), 1),
               fmt(r.stat("cpu_sub"), 1), fmt(r.stat("loop_late_p99"), 1)] if cpu else []),
        ])
    return markdown_table(headers, rows)


#: p50 at 1 kHz over the raw UDP pair's p50 of the same run (issue #18, default idle strategy).
P50_TARGET = 3


def targets(results: Sequence[CaseResult]) -> list[str]:
    """At 1 kHz: p50 <= 3 x raw UDP p50 (#18, default idle strategy) and p99 <= ZeroMQ p99."""
    lines = []
    for r in results:
        if r.case.kind != "rlbridge" or r.rate_hz != 1000.0 or not r.runs:
            continue
        udp, zmq = _peer(results, r, "udp"), _peer(results, r, "zmq")
        if udp is not None:
            x = ratio(r.stat("p50"), udp.stat("p50"))
            lines.append(f"- {r.case.label} at 1 kHz: p50 = {fmt(x, 2)} x raw UDP; target "
                         f"<= {P50_TARGET}: **{'met' if x <= P50_TARGET else 'not met'}**")
        if zmq is not None:
            x = ratio(r.stat("p99"), zmq.stat("p99"))
            lines.append(f"- {r.case.label} at 1 kHz: p99 = {fmt(x, 2)} x ZeroMQ; target "
                         f"<= 1: **{'met' if x <= 1 else 'not met'}**")
    return lines


def report(results: Sequence[CaseResult], settings: Settings, command: Sequence[str]) -> str:
    """The markdown section ``rlbridge bench latency --out`` writes."""
    per_run = (f"{settings.count:,} samples" if settings.count is not None
               else f"{settings.seconds:g} s")
    parts = [
        report_header("Latency by SDK idle strategy" if settings.idle else "Latency", command),
        f"{settings.repeats} repeats per row, interleaved; {per_run} per run after "
        f"{WARMUP} warm-up samples. One-way latency = subscriber's `time.time_ns()` when a "
        "blocking read returns the value, minus the publisher's `time.time_ns()` written into "
        "it (same machine, same clock). Percentiles per run, then the median over repeats. "
        "rlbridge: publisher -> server -> subscriber (2 hops, 3 processes); baselines: 1 hop. "
        "The publisher writes each value to an immediate channel (the write wakes the SDK's "
        "send thread), except `send(inline=True)`: a buffered channel and "
        "`bridge.send(inline=True)` after each write, the round sent from the loop's thread. "
        "The two legs split each rlbridge sample at the server's send stamp "
        "(`IncomingChannel.last_stamp_ns`): publisher write -> server send includes the "
        "publisher's send-thread wake-up, hop 1 and the server; server send -> read includes "
        "hop 2, the receive thread and the reader's wake-up."
        + (" Idle rows: the SDK threads of publisher and subscriber wait by that strategy "
           "(`Tuning(idle=...)`); CPU % = user + system time of each whole process "
           "over the stream, in % of one core; `pub loop late` = p99 of how late the "
           "publisher's paced loop woke for its next write (its own GIL and scheduler wait)."
           if settings.idle else ""),
        "",
        table(results),
        "",
        "Targets:",
        "",
        *targets(results),
    ]
    return "\n".join(parts) + "\n"
