"""``rlbridge bench throughput``: values per second through the bridge, next to baselines.

The rlbridge path is the deployed one, three processes and two hops: an SDK publisher writes
``std_msgs/msg/Float64`` values into an outgoing channel; the bridge server (the in-process bus
as its middleware) hands them to the subscription of a second client; that SDK subscriber reads
them from a blocking incoming channel. The baselines (raw UDP, ZeroMQ, Zenoh) are one hop, two
processes, 8-byte messages, from the same run.

Two shapes of traffic:

* ``batch == 1``, one value per packet: the publisher calls ``write`` per value and the server
  runs with ``max_batch=1``, so every packet on both hops (TCP frame, UDP ``Value``) carries
  exactly one value. On UDP the values a send round (or a server loop iteration) finds travel
  together in bundles; the ``bundles=False`` row sends one datagram per value, both ways.
  Compared with the raw UDP loop's datagrams per second.
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
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from rlbridge.bench import baselines
from rlbridge.bench.common import (
    STARTUP_S,
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
    hold,
    median,
    run_flow,
    select_cases,
    start_server,
    wait_for_go,
)
from rlbridge.csp.options import Policy, Tuning

if TYPE_CHECKING:
    from rlbridge.csp.bridge import Bridge
    from rlbridge.csp.bridge_channels import OutgoingChannel

MODULE = "rlbridge.bench.throughput"
TOPIC = "/bench/throughput"
MSG_TYPE = "std_msgs/msg/Float64"
SUB_BUFFER = 1 << 18


@dataclass(frozen=True)
class Case:
    """One row: ``kind`` is ``rlbridge`` or a baseline (``udp``, ``zmq``, ``zenoh``)."""

    key: str
    label: str
    kind: str
    transport: str = "udp"
    batch: int = 1
    #: > 0: the subscriber reads at most this many values per second (a slow reader).
    sub_rate: float = 0.0
    #: Credit flow control on the TCP channel (None: the SDK's default).
    flow: bool | None = None
    #: ``send`` / ``send-wait``: a loop of ``write_many`` + ``Bridge.send()`` (``wait=True``)
    #: that never yields, through a buffered channel (the GIL-starvation case).
    send_form: str = ""
    #: The publisher's SDK idle strategy (csp/idle.py).
    idle: str = "park"
    #: ``Tuning(bundles=...)`` of both clients (UDP rows).
    bundles: bool = True


#: Seconds without an arrival after which a subscriber of a flow-controlled TCP row calls
#: what is missing lost (other rows: ``Settings.idle_s``). The rate is not affected: it is
#: measured to the last arrival.
EVERY_VALUE_IDLE_S = 5.0

#: The slow subscriber of the flow-control rows: values/s it reads, and its ring.
SLOW_RATE = 100_000.0
SLOW_BUFFER = 4096


def cases(batch: int = 4096) -> tuple[Case, ...]:
    """Every row, in report order; ``batch`` is the ``write_many`` size of the batched rows."""
    return (
        Case("udp", "raw UDP socket, 1 hop", "udp"),
        Case("zmq", "ZeroMQ PUB/SUB tcp, 1 hop", "zmq"),
        Case("zenoh", "Zenoh peer tcp, 1 hop", "zenoh"),
        Case("rlb-udp-1", "rlbridge UDP, write per value, bundles", "rlbridge", "udp", 1),
        Case("rlb-udp-1-single", "rlbridge UDP, 1 value/datagram (bundles=False)", "rlbridge",
             "udp", 1, bundles=False),
        Case("rlb-tcp-1", "rlbridge TCP, 1 value/frame", "rlbridge", "tcp", 1),
        Case("rlb-udp-batch", f"rlbridge UDP, write_many({batch})", "rlbridge", "udp", batch),
        Case("rlb-tcp-batch", f"rlbridge TCP, write_many({batch})", "rlbridge", "tcp", batch),
        Case("rlb-tcp-batch-noflow", f"rlbridge TCP, write_many({batch}), flow=False",
             "rlbridge", "tcp", batch, flow=False),
        Case("rlb-tcp-slow-flow", f"rlbridge TCP, write_many(1024), reader at "
             f"{SLOW_RATE:,.0f}/s, flow control", "rlbridge", "tcp", 1024, SLOW_RATE, True),
        Case("rlb-tcp-slow-noflow", f"rlbridge TCP, write_many(1024), reader at "
             f"{SLOW_RATE:,.0f}/s, flow=False", "rlbridge", "tcp", 1024, SLOW_RATE, False),
        *(Case(f"rlb-tcp-{form}{'' if idle == 'park' else '-' + idle}",
               f"rlbridge TCP, loop of write_many(1024) + "
               f"{'send()' if form == 'send' else 'send(wait=True)'}, idle={idle}",
               "rlbridge", "tcp", 1024, 0.0, None, form, idle)
          for form in ("send", "send-wait") for idle in ("park", "spin")),
    )


# -- worker roles (child processes) --------------------------------------------------------
def _write_loop(out: OutgoingChannel, batch: int, high: int, count: int, seconds: float,
                rate: float, half: list[float] | None = None) -> tuple[int, float]:
    """Write ``count`` values (or for ``seconds``); return how many and the start time.

    Waits while more than ``high`` values are unsent (the ring would otherwise overwrite
    them); with ``rate`` > 0 it also keeps to that many values per second. ``half`` gets
    ``[time, sent]`` at half time and at the end: the rate once the path is full.
    """
    values = [float(i) for i in range(batch)]
    sent = 0
    start = time.monotonic()
    end = start + seconds
    while sent < count and time.monotonic() < end:
        if half is not None and not half and time.monotonic() >= start + seconds / 2:
            half += [time.monotonic(), sent]
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
    if half:
        half += [time.monotonic(), sent]
    return sent, start


def _send_loop(bridge: Bridge, out: OutgoingChannel, batch: int, count: int, seconds: float,
               *, wait: bool) -> tuple[int, float]:
    """``write_many`` + ``send()`` as fast as the loop goes, never sleeping: what a control
    loop that never yields does to the send thread (it needs the GIL too)."""
    values = [float(i) for i in range(batch)]
    sent = 0
    start = time.monotonic()
    end = start + seconds
    while sent < count and time.monotonic() < end:
        out.write_many(values)
        bridge.send(wait=wait)
        sent += batch
    return sent, start


def publisher(params: Params) -> None:
    """SDK publisher: ``write`` per value (batch 1) or ``write_many`` of ``batch`` values."""
    from rlbridge.csp.bridge import Bridge

    control = Control()
    batch = int(params["batch"])
    buffer = max(4 * batch, 1 << 16)
    form = str(params.get("send_form", ""))
    half: list[float] = []
    bridge = Bridge.connect(params["host"], int(params["port"]), name="bench-pub",
                            tuning=Tuning(bundles=bool(params.get("bundles", True)),
                                          idle=str(params.get("idle", "park"))))
    out = bridge.publish(TOPIC, MSG_TYPE, "data", transport=params["transport"],
                         buffer_size=buffer, policy=Policy(flow=params.get("flow")),
                         through_buffer=bool(form))
    emit("ready")
    wait_for_go(control)
    if form:
        sent, start = _send_loop(bridge, out, batch, int(params["count"]),
                                 float(params["seconds"]), wait=form == "send-wait")
    else:
        sent, start = _write_loop(out, batch, buffer // 2, int(params["count"]),
                                  float(params["seconds"]), float(params.get("rate", 0.0)), half)
    drained = time.monotonic() + 120.0  # flow control: what waits leaves at the reader's pace
    while out.pending() and time.monotonic() < drained:
        bridge.send()  # a buffered channel's values leave only on send()
        time.sleep(0.001)
    bridge.send(wait=True)
    stats = out.statistics()
    steady = (half[3] - half[1]) / (half[2] - half[0]) if len(half) == 4 else None
    emit("sent", sent=sent, t_start=start, t_end=time.monotonic(), written=stats.written,
         steady_rate=steady,
         overwritten=stats.overwritten, taken=stats.read)
    control.wait("stats", 120.0)
    channel = bridge.server_stats()["session"]["channels"][str(out.channel_id)]
    emit("stats", values_in=channel["values_in"], lost=channel["lost"],
         reconnects=bridge.reconnects,
         bad_values=channel["bad_values"])
    hold(control)


def subscriber(params: Params) -> None:
    """SDK subscriber: blocking ``read`` then ``read_many`` of everything else waiting."""
    from rlbridge.csp.bridge import Bridge

    control = Control()
    sub_rate = float(params.get("sub_rate", 0.0))
    bridge = Bridge.connect(params["host"], int(params["port"]), name="bench-sub",
                            tuning=Tuning(bundles=bool(params.get("bundles", True))))
    ch = bridge.subscribe(TOPIC, MSG_TYPE, "data", transport=params["transport"],
                          blocking=True, buffer_size=SLOW_BUFFER if sub_rate else SUB_BUFFER,
                          policy=Policy(flow=params.get("sub_flow")))
    emit("ready")
    emit("joined")
    tally = Tally(control, float(params["idle_s"]))
    read, read_many, mono = ch.read, ch.read_many, time.monotonic
    chunk = max(1, int(sub_rate / 1000)) if sub_rate else None  # a slow reader: 1 ms steps
    while not tally.done(mono()):
        try:
            read(0.05)
        except TimeoutError:
            continue
        tally.add(1 + len(read_many(chunk)), mono())
        if sub_rate:
            delay = tally.t_first + tally.received / sub_rate - mono()
            if delay > 0:
                time.sleep(delay)
    stats = ch.statistics()
    out = bridge.server_stats()["session"]["channels"][str(ch.channel_id)]
    tally.report(lost=ch.lost, duplicates=ch.duplicates, overwritten=stats.overwritten,
                 reconnects=bridge.reconnects,
                 arrived=stats.written, values_out=out["values_out"], dropped=out["dropped"])
    hold(control)


ROLES: dict[str, Role] = {"publisher": publisher, "subscriber": subscriber}


# -- one measurement (parent) --------------------------------------------------------------
@dataclass
class Measurement:
    """One repeat of one case: rate, CPU per million values by process, losses by stage."""

    rate: float
    cpu: dict[str, float]
    written: int
    loss: dict[str, int] = field(default_factory=dict)
    #: Loss counted another way (sequence gaps, refusals): shown, not added up.
    seen: dict[str, int] = field(default_factory=dict)
    #: Values the publisher wrote per second (rlbridge rows; its ring drained at the end).
    pub_rate: float = math.nan

    @property
    def lost_fraction(self) -> float:
        return self.loss.get("end to end", 0) / self.written if self.written else math.nan


def _rlbridge_once(group: ProcessGroup, case: Case, count: int, seconds: float,
                   idle_s: float, timeout: float, rate: float) -> Measurement:
    # A 5 s watchdog: under a flood on a loaded machine the default 600 ms one can end a
    # session, and a new binding restarts the server's counters (the stages below would not
    # add up; such runs are marked).
    server, host, port = start_server(group, max_batch=case.batch, timeout_ms=5000)
    common: Params = {"host": host, "port": port, "transport": case.transport,
                      "sub_rate": case.sub_rate, "flow": case.flow,
                      "sub_flow": case.flow,
                      "send_form": case.send_form, "idle": case.idle,
                      "bundles": case.bundles}
    if case.transport == "tcp" and case.flow is not False:
        # Every value is promised here: a pause is a late value, not a lost one. On a loaded
        # machine the path can stall for half a second with values still in the server's
        # backlog; they would be counted lost if the subscriber stopped waiting then.
        idle_s = max(idle_s, EVERY_VALUE_IDLE_S)
    sub = group.start("subscriber", "b", MODULE, "subscriber", {**common, "idle_s": idle_s})
    pub = group.start("publisher", "b", MODULE, "publisher",
                      {**common, "batch": case.batch, "count": count, "seconds": seconds,
                       "rate": rate})
    for worker in (sub, pub):  # started together; the publisher waits for "go" anyway
        worker.expect("ready", STARTUP_S)
    flow = run_flow(pub, sub, [pub, server, sub], timeout, expect_key="taken")
    pub.send("stats")
    hop1 = pub.expect("stats", 30.0)
    got = flow.received
    taken = int(flow.sent["taken"])
    written, values_in = int(flow.sent["written"]), int(hop1["values_in"])
    values_out, arrived = int(got["values_out"]), int(got["arrived"])
    # Stages partition the loss: each is "in at this stage" minus "in at the next", so they
    # add up to the end-to-end figure by construction and none goes below zero.
    loss = {
        "publisher ring": written - taken,
        "hop 1 (publisher -> server)": taken - values_in,
        "server (accepted, never sent)": values_in - values_out,
        "hop 2 (server sent, never arrived)": values_out - arrived,
        "subscriber ring (arrived, never read)": arrived - int(got["received"]),
        "end to end": written - int(got["received"]),
    }
    # The same loss seen another way (not added): sequence gaps at each receiver, and the
    # values the server's TCP buffer refused (part of hop 2 above).
    restarts = int(hop1.get("reconnects", 0)) + int(got.get("reconnects", 0))
    if restarts:  # the server's counters restarted with the new bindings: no stages
        loss = {"end to end": written - int(got["received"])}
    seen = {"session restarts (stages not known)": restarts,
            "hop 1 gaps (server)": int(hop1["lost"]),
            "hop 2 gaps (IncomingChannel.lost)": int(got["lost"]),
            "of hop 2: dropped by the server (send buffer or backlog full)": int(got["dropped"])}
    # The publisher's rate once the path is full (its second half), else over the whole run.
    pub_rate = flow.sent.get("steady_rate") or \
        written / max(1e-9, float(flow.sent["t_end"]) - float(flow.sent["t_start"]))
    return _measurement(flow, written, loss, seen, pub_rate)


def _baseline_once(group: ProcessGroup, case: Case, count: int, seconds: float,
                   idle_s: float, timeout: float, rate: float) -> Measurement:
    tx, rx = baselines.spawn_pair(group, case.kind, {"mode": "flood", "count": count,
                                                     "seconds": seconds, "idle_s": idle_s})
    flow = run_flow(tx, rx, [tx, rx], timeout)
    sent = int(flow.sent["sent"])
    return _measurement(flow, sent, {"end to end": sent - int(flow.received["received"])})


def _measurement(flow: Flow, written: int, loss: dict[str, int],
                 seen: dict[str, int] | None = None, pub_rate: float = math.nan) -> Measurement:
    cpu = {name: flow.cpu_per_million(name) for name in flow.cpu_s}
    cpu["total"] = sum(cpu.values())
    return Measurement(flow.rate, cpu, written, loss, seen or {}, pub_rate)


def measure(link: Link, case: Case, *, count: int, seconds: float, idle_s: float = 0.5,
            timeout: float = 120.0, rate: float = 0.0) -> Measurement:
    """One repeat of ``case`` over ``link``, in fresh processes that are all gone after it."""
    once = _rlbridge_once if case.kind == "rlbridge" else _baseline_once
    with ProcessGroup(link, lifetime_s=seconds + timeout + 60) as group:
        try:
            return once(group, case, count, seconds, idle_s, timeout, rate)
        except BenchError as exc:
            raise BenchError(f"{exc}{group.diagnostics()}") from None


# -- runs and report -----------------------------------------------------------------------
@dataclass(frozen=True)
class Settings:
    """What ``rlbridge bench throughput`` was asked for (also printed in the report)."""

    count: int = 2_000_000
    seconds: float = 3.0
    repeats: int = 3
    batch: int = 4096
    rate: float = 0.0
    idle_s: float = 0.5
    only: tuple[str, ...] = ()


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


def run(link: Link, settings: Settings,
        progress: Callable[[str], None] | None = None) -> list[CaseResult]:
    """Every selected case ``repeats`` times, interleaved so a noisy minute hits every row."""
    selected = select_cases(cases(settings.batch), settings.only)
    results = [CaseResult(c) for c in selected]
    for rep in range(settings.repeats):
        for res in results:
            if res.skipped is not None:
                continue
            if progress is not None:
                progress(f"throughput {rep + 1}/{settings.repeats}: {res.case.label}")
            try:
                res.runs.append(measure(link, res.case, count=settings.count,
                                        seconds=settings.seconds, idle_s=settings.idle_s,
                                        rate=settings.rate))
            except Skipped as exc:
                res.skipped = str(exc)
            except BenchError as exc:
                raise BenchError(f"{res.case.label}: {exc}") from None
    return results
