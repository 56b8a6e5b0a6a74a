"""``rlbridge bench latency --stages``: where the time of one value goes, stage by stage.

The same stream as ``rlbridge bench latency`` (a publisher writes ``time.time_ns()`` at 1 kHz,
a subscriber blocks in ``read``), rlbridge UDP only, with probes in both SDK processes. Every
probe is a ``time.time_ns()`` (one clock for the whole machine), keyed by the value, which is
the publisher's write time and so unique:

* publisher: the send thread comes back from its idle strategy (a wrapping
  :class:`ProbeIdle`), and the round that took the value calls ``sendto`` and is back;
* server: the stamp it puts on the value for the subscriber (when it hands the value on);
* subscriber: the receive thread comes back from its idle strategy (``select`` returned),
  the value reaches ``Connection.on_values`` (``recv``, decode, dispatch, gather done), that
  call returns (sequence check, ring write, doorbell), and the blocking ``read`` returns.

The probes wrap methods of the SDK objects of the child processes only, no production code
path carries them; those processes run rlbridge's modules as Python files
(``RLBRIDGE_PURE_PYTHON``: a compiled module's calls would not see the wrappers). Each
stage's p50 is a median over the samples of a run, then over the runs; the stages of one
sample add up to its total, their medians need not.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from rlbridge.bench import latency
from rlbridge.bench.common import (
    BenchError,
    Control,
    Link,
    Params,
    ProcessGroup,
    Role,
    Tally,
    emit,
    fmt,
    hold,
    markdown_table,
    median,
    paced,
    percentile,
    report_header,
    rlbridge_flow,
    wait_for_go,
)
from rlbridge.bench.latency import MSG_TYPE, TOPIC, WARMUP
from rlbridge.cli.options import tuning_of
from rlbridge.client.options import Tuning
from rlbridge.csp.idle import IdleStrategy, idle_pair

MODULE = "rlbridge.bench.latency_stages"
T = TypeVar("T")

#: (label, start probe, end probe) of each row; probes named as in the records below.
STAGES = (
    ("`write` -> the send thread is back from its idle strategy", "write", "send_woke"),
    ("-> its datagram is ready (take, encode)", "send_woke", "sendto"),
    ("-> `sendto` returns (the system call, loopback delivery)", "sendto", "sent"),
    ("-> the server stamps it for the subscriber (hop 1, server wake-up, server)", "sendto",
     "server"),
    ("-> the receive thread is back from its idle strategy (hop 2, wake-up)", "server",
     "recv_woke"),
    ("-> the values reach `on_values` (`recv`, decode, dispatch)", "recv_woke", "on_values"),
    ("-> `on_values` returns (sequence check, ring write, doorbell)", "on_values", "delivered"),
    ("-> the blocking `read` returns (the reader's wake-up, GIL)", "delivered", "read"),
    ("total: `write` -> `read` returns", "write", "read"),
)


class ProbeIdle:
    """An idle strategy around another that notes when its thread comes back with work."""

    def __init__(self, inner: IdleStrategy) -> None:
        self.inner = inner
        self.name = f"probe({inner.name})"
        self.woke = 0

    def idle(self, poll: Callable[[], T], block: Callable[[float | None], T],
             timeout: float | None) -> T:
        """The wrapped strategy's wait, then the wake-up time."""
        got = self.inner.idle(poll, block, timeout)
        self.woke = time.time_ns()
        return got


def _connect(params: Params, name: str) -> tuple[Any, ProbeIdle, ProbeIdle]:
    from rlbridge.client.bridge import Bridge

    send, receive = idle_pair(tuning_of(idle=str(params["idle"])).idle)
    probes = ProbeIdle(send), ProbeIdle(receive)
    bridge = Bridge.connect(params["host"], int(params["port"]), name=name,
                            tuning=Tuning(idle=probes))
    return bridge, probes[0], probes[1]


def publisher(params: Params) -> None:
    """A paced writer; the send thread's wake-up and datagram times per value."""
    from rlbridge.client.channels.outgoing import OutgoingChannel
    from rlbridge.client.session import plain_round
    from rlbridge.client.session import sender as send_module
    from rlbridge.wire.bundle import VALUE_TAG

    control = Control()
    bridge, send_probe, _ = _connect(params, "bench-stages-pub")
    out = bridge.publish(TOPIC, MSG_TYPE, "data", transport="udp")
    taken: list[int] = []
    take = OutgoingChannel.take

    def probed_take(self: OutgoingChannel, congested: bool = False) -> Any:
        got = take(self, congested)
        taken.extend(got[2])
        return got

    OutgoingChannel.take = probed_take  # type: ignore[method-assign]  # this process only
    take_plain = plain_round.take_plain

    def probed_take_plain(channels: Any, parts: list[Any], max_batch: int) -> int:
        first = len(parts)
        n = take_plain(channels, parts, max_batch)
        for part in parts[first:]:  # a Value's fields, or a Batch's (its values a list)
            if part[0] == VALUE_TAG:
                taken.append(part[-1])
            else:
                taken.extend(part[-1])
        return n

    vars(send_module)["take_plain"] = probed_take_plain  # the plain channels' round
    conn = bridge._conn  # a probe: this process only
    send_udp = conn.send_udp
    last_send = [0, 0]  # the send thread's last sendto: called, returned

    def probed_send_udp(data: bytes) -> None:
        start = time.time_ns()
        send_udp(data)
        last_send[:] = start, time.time_ns()

    conn.send_udp = probed_send_udp  # type: ignore[method-assign,unused-ignore]  # first
    sender = bridge._sender
    send_pending = sender._send_pending
    records: list[tuple[int, int, int, int]] = []  # value, send thread woke, sendto, returned

    def probed_send_pending(flush_all: bool) -> None:
        first = len(taken)
        send_pending(flush_all)
        called, returned = last_send
        records.extend((v, send_probe.woke, called, returned) for v in taken[first:])

    sender._send_pending = probed_send_pending
    emit("ready")
    wait_for_go(control)
    sent, t0, t1 = paced(out.write, float(params["rate_hz"]), int(params["count"]))
    time.sleep(0.05)  # the last round's record
    emit("sent", sent=sent, t_start=t0, t_end=t1, records=records)
    hold(control)


def subscriber(params: Params) -> None:
    """Blocking reads; the receive thread's probes per value."""
    control = Control()
    bridge, _, recv_probe = _connect(params, "bench-stages-sub")
    ch = bridge.subscribe(TOPIC, MSG_TYPE, "data", transport="udp", blocking=True,
                          buffer_size=1024)
    conn = bridge._conn  # a probe: this process only
    on_values = conn.on_values
    assert on_values is not None
    now_ns = time.time_ns
    records: list[tuple[int, int, int, int, int]] = []  # value, server, woke, on_values, out

    def probed(channel: int, first_seq: int, stamps: list[int], values: list[Any]) -> None:
        start = now_ns()
        pairs = list(zip(stamps, values, strict=True))
        on_values(channel, first_seq, stamps, values)
        end = now_ns()
        woke = recv_probe.woke
        records.extend((v, s, woke, start, end) for s, v in pairs)

    conn.on_values = probed
    emit("ready")
    emit("joined")
    tally = Tally(control, float(params["idle_s"]))
    reads: list[tuple[int, int]] = []
    read, mono = ch.read, time.monotonic
    while not tally.done(mono()):
        try:
            value = read(0.05)
        except TimeoutError:
            continue
        reads.append((value, now_ns()))
        tally.add(1, mono())
    tally.report(reads=reads, records=records)


ROLES: dict[str, Role] = {"publisher": publisher, "subscriber": subscriber}


# -- parent ----------------------------------------------------------------------------------
@dataclass
class StageRun:
    """One run: per stage, the p50 in microseconds; and the raw UDP pair's p50 next to it."""

    p50: dict[str, float]
    samples: int


def _stage_p50s(pub_records: list[list[int]], sub_records: list[list[int]],
                reads: list[list[int]]) -> StageRun:
    pub = {r[0]: r for r in pub_records}
    sub = {r[0]: r for r in sub_records}
    per_stage: dict[str, list[float]] = {label: [] for label, _, _ in STAGES}
    kept = 0
    for value, read_ns in reads[WARMUP:]:
        p, s = pub.get(value), sub.get(value)
        if p is None or s is None:
            continue
        kept += 1
        at = {"write": value, "send_woke": p[1], "sendto": p[2], "sent": p[3], "server": s[1],
              "recv_woke": s[2], "on_values": s[3], "delivered": s[4], "read": read_ns}
        for label, start, end in STAGES:
            per_stage[label].append((at[end] - at[start]) / 1000.0)
    return StageRun({label: percentile(sorted(xs), 50) if xs else math.nan
                     for label, xs in per_stage.items()}, kept)


def measure(link: Link, idle: str, rate_hz: float, count: int) -> StageRun:
    """One probed run of rlbridge UDP with SDK idle strategy ``idle``."""
    stream: Params = {"rate_hz": rate_hz, "count": count, "idle_s": 0.5, "idle": idle}
    timeout = count / rate_hz + 30.0
    with ProcessGroup(link, lifetime_s=timeout + 120) as group:
        try:
            # The probes wrap the SDK's Python functions: its Python files, not compiled.
            flow = rlbridge_flow(group, MODULE, stream, timeout, python_files=True)
        except BenchError as exc:
            raise BenchError(f"{exc}{group.diagnostics()}") from None
    return _stage_p50s(flow.sent["records"], flow.received["records"], flow.received["reads"])


def raw_udp_p50(link: Link, rate_hz: float, count: int) -> float:
    """The raw UDP pair's p50 (us) of a run in the same series: the unit of the targets."""
    return latency.measure(link, latency.RAW_UDP, rate_hz=rate_hz, count=count).p50


@dataclass
class StageResult:
    idle: str
    runs: list[StageRun] = field(default_factory=list)


def run(link: Link, strategies: Sequence[str], *, seconds: float, repeats: int,
        rate_hz: float = 1000.0,
        progress: Callable[[str], None] | None = None) -> tuple[list[StageResult], list[float]]:
    """Each strategy ``repeats`` times, interleaved with a raw UDP pair run per repeat."""
    count = max(10, int(seconds * rate_hz)) + WARMUP
    results = [StageResult(s) for s in strategies]
    raw: list[float] = []
    for rep in range(repeats):
        if progress is not None:
            progress(f"stages {rep + 1}/{repeats}: raw UDP")
        raw.append(raw_udp_p50(link, rate_hz, count))
        for res in results:
            if progress is not None:
                progress(f"stages {rep + 1}/{repeats}: rlbridge UDP, idle={res.idle}")
            res.runs.append(measure(link, res.idle, rate_hz, count))
    return results, raw


def report(results: Sequence[StageResult], raw: Sequence[float], *, seconds: float,
           repeats: int, rate_hz: float, command: Sequence[str]) -> str:
    """The markdown section ``--stages --out`` writes: one column per idle strategy."""
    headers = ["stage (p50, us)", *(f"idle={r.idle}" for r in results)]
    rows = [[label, *(fmt(median([run.p50[label] for run in r.runs]), 1) for r in results)]
            for label, _, _ in STAGES]
    raw_p50 = median(list(raw))
    rows.append(["for comparison: raw UDP socket pair, one hop (same series)",
                 *(fmt(raw_p50, 1) for _ in results)])
    rows.append(["total p50 / raw UDP p50",
                 *(fmt(median([run.p50[STAGES[-1][0]] for run in r.runs]) / raw_p50, 2)
                   for r in results)])
    return "\n".join([
        report_header("Latency by stage", command),
        f"rlbridge UDP at {rate_hz:g} Hz, {repeats} repeats interleaved with a raw UDP pair "
        f"run, {seconds:g} s per run after {WARMUP} warm-up samples. Probes (`time.time_ns()` "
        "in the SDK processes, wrapped around the send thread's round, the receive thread's "
        "idle strategy and `Connection.on_values`; the server's stamp) split each sample; "
        "each cell is the median over runs of the per-run p50 of that stage, so the column "
        "need not add up to the total exactly.",
        "",
        markdown_table(headers, rows),
    ]) + "\n"
