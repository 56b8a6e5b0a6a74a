"""``rlbridge bench load``: many concurrent clients on one server, and a consumer that stalls.

``clients`` sessions with ``channels`` channels each publish at ``rate_hz`` and subscribe to what
they publish, spread over ``processes`` OS processes (``load_roles``: SDK sessions; ``load_raw``:
protocol-level sessions), all on one server process on loopback. The run is cut into phases of
equal length, measured one after the other in the same run:

* ``base``: the clients alone;
* ``reader``: plus a consumer of the same topics as the slow one below, fed the same way,
  that reads everything: the control for ``slow`` (the same server work, minus the stall);
* ``slow``: instead, a consumer that subscribes over TCP to ``slow_topics`` of the clients' topics
  and to a bulk topic, and never reads: the server's queue to it must stay bounded
  (``max_write_buffer``), the excess be dropped and counted, the server's memory stay flat, and
  the other sessions' latency stay;
* ``after``: the slow consumer has gone again (a second baseline, for the noise).

Per phase: offered and delivered values/s, latency p50/p99 per session, server CPU (and the
time it waited for one: this machine is shared) and RSS sampled every second, and the server's
own counters (``Stats``). The parent only coordinates: it sleeps between samples.
"""

from __future__ import annotations

import math
import os
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from rlbridge.bench.common import (
    BenchError,
    Link,
    LoopbackLink,
    Params,
    ProcessGroup,
    Worker,
    cpu_seconds,
    fmt,
    markdown_table,
    median,
    report_header,
    start_server,
)
from rlbridge.bench.load_sockets import udp_drops, udp_queued
from rlbridge.bench.load_stages import KernelDrops, stage_table, stages
from rlbridge.server.config import UDP_RECEIVE_BUFFER
from rlbridge.sockbuf import BufferGrant, request_buffer

MODULE = "rlbridge.bench.load_roles"
MiB = 1 << 20


def run_delay_s(pid: int) -> float:
    """Seconds the process's main thread was runnable but waiting for a CPU (schedstat)."""
    with open(f"/proc/{pid}/schedstat") as f:
        return int(f.read().split()[1]) / 1e9


def rss_bytes(pid: int) -> int:
    """Resident set size of a live process (``VmRSS`` in ``/proc/<pid>/status``)."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


@dataclass(frozen=True)
class Settings:
    clients: int = 100
    channels: int = 10
    rate_hz: float = 100.0
    processes: int = 4
    transport: str = "udp"
    #: ``raw``: protocol-level sessions, one thread per process (``load_raw``); ``sdk``: Bridge.
    client: str = "raw"
    #: Every channel of a session's tick in one datagram, both ways (``False``: one per value).
    bundles: bool = True
    phase_s: float = 20.0
    warmup_s: float = 5.0
    slow_topics: int = 100
    #: Values/s fed (in batches) to a bulk topic only the slow consumer subscribes to.
    bulk_rate: float = 40_000.0
    max_write_buffer: int = 256 << 10
    #: The clients read until nothing arrives for 2 s, at most this long, after the last phase.
    drain_s: float = 60.0
    #: The server's ``udp_receive_buffer`` (bytes asked for its UDP socket).
    udp_receive_buffer: int = UDP_RECEIVE_BUFFER
    #: Niceness the client processes add to their own (0-19): the load generator yields the
    #: CPU to the server it measures, as clients on other machines would not take it.
    client_nice: int = 0
    #: A client process behind schedule writes its late ticks up to this far behind; beyond,
    #: it skips them (counted as the generator's shortfall).
    catch_up_s: float = 0.1

    @property
    def offered(self) -> float:
        return self.clients * self.channels * self.rate_hz


@dataclass
class Phase:
    """What the parent saw over one phase (the clients' view is added from their results)."""

    name: str
    seconds: float
    cpu_s: float
    clients_cpu_s: float
    wait_s: float
    rss: list[int]
    stats0: Params
    stats1: Params
    sessions: list[Params] = field(default_factory=list)
    #: Datagrams the kernel dropped on the server's and the clients' sockets in the phase.
    kernel: KernelDrops = field(default_factory=KernelDrops)
    #: Bytes waiting in the server's UDP receive queue, sampled every second (kernel memory).
    queued: list[int] = field(default_factory=list)

    def server_delta(self, key: str) -> int:
        return int(self.stats1["server"].get(key, 0) - self.stats0["server"].get(key, 0))

    def named(self, name: str) -> Params | None:
        return next((s for s in self.stats1.get("sessions", []) if s["name"] == name), None)


@dataclass
class Run:
    settings: Settings
    phases: list[Phase]
    results: list[Params]
    skipped_ticks: int
    load_before: tuple[float, float, float]
    load_after: tuple[float, float, float]
    #: Kernel drops from the clients' "go" to their results (the whole run).
    kernel: KernelDrops = field(default_factory=KernelDrops)
    #: What a UDP socket of this machine gets when it asks as the server does.
    grant: BufferGrant | None = None
    #: The server's ``Stats`` once the clients have drained: a gap is counted when the value
    #: after it arrives, which can be seconds after the last phase behind a deep queue.
    final_stats: Params | None = None


#: A phase plan: (name, seconds, what to do with the slow consumer first: start/stop/None).
Plan = Sequence[tuple[str, float, str | None]]


def load_plan(s: Settings) -> Plan:
    return [("base", s.phase_s, None), ("reader", s.phase_s, "reader"),
            ("slow", s.phase_s, "stalled"), ("after", s.phase_s, None)]


def run(settings: Settings, plan: Plan, progress: Callable[[str], None],
        link: Link | None = None) -> Run:
    """Start everything, measure ``plan`` phase by phase, stop everything (also on errors)."""
    s = settings
    total_s = s.warmup_s + sum(p[1] for p in plan)
    load_before = os.getloadavg()
    group = ProcessGroup(link or LoopbackLink(), lifetime_s=total_s + 600)
    with group:
        try:
            return _run(group, s, plan, progress, total_s, load_before)
        except BenchError as exc:
            raise BenchError(f"{exc}{group.diagnostics()}") from None


def _run(group: ProcessGroup, s: Settings, plan: Plan, progress: Callable[[str], None],
         total_s: float, load_before: tuple[float, float, float]) -> Run:
    from rlbridge.client.bridge import Bridge

    server, host, port = start_server(group, max_write_buffer=s.max_write_buffer,
                                      heartbeat_ms=500, timeout_ms=5000,
                                      udp_receive_buffer=s.udp_receive_buffer)
    ids = list(range(s.clients))
    per = [ids[i :: s.processes] for i in range(s.processes)]
    common = {"host": host, "port": port, "channels": s.channels, "rate_hz": s.rate_hz,
              "transport": s.transport, "max_s": total_s + 60, "drain_s": s.drain_s,
              "bundles": s.bundles, "nice": s.client_nice, "catch_up_s": s.catch_up_s}
    role = "raw" if s.client == "raw" else "clients"
    workers = [group.start(f"clients-{i}", "b", MODULE, role, {**common, "ids": chunk})
               for i, chunk in enumerate(per) if chunk]
    for w in workers:
        w.expect("ready", 300)
    progress(f"{s.clients} sessions x {s.channels} channels connected; warming up")

    def kernel() -> KernelDrops:
        return KernelDrops(udp_drops([server.pid]), udp_drops([w.pid for w in workers]))

    kernel0 = kernel()
    with Bridge.connect(host, port, name="load-stats", timeout=30.0) as probe:
        for w in workers:
            w.send("go")
        time.sleep(s.warmup_s)
        phases: list[Phase] = []
        slow: Worker | None = None
        for name, seconds, action in plan:
            if slow is not None:
                slow.stop()
                slow = None
            if action is not None:
                topics = [f"/load/s{i % s.clients}/c{1 + (i // s.clients) % max(1, s.channels - 1)}"
                          for i in range(s.slow_topics)]
                slow, _ = group.spawn("slow", "b", MODULE, "slow",
                                      {"host": host, "port": port, "topics": topics,
                                       "bulk_rate": s.bulk_rate, "max_s": total_s + 60,
                                       "stall": action == "stalled"}, timeout=60)
            k0 = kernel()
            phases.append(_phase(name, seconds, workers, server, probe))
            phases[-1].kernel = kernel() - k0
            progress(f"phase {name}: done")
        for w in workers:
            w.send("stop")
        results = [w.expect("result", 120 + s.drain_s) for w in workers]
        final = probe.server_stats()
    drops = kernel() - kernel0
    for phase in phases:
        phase.sessions = [r for res in results for r in res["sessions"]]
    return Run(s, phases, [r for res in results for r in res["sessions"]],
               sum(int(r["skipped"]) for r in results), load_before, os.getloadavg(),
               drops, _grant(s.udp_receive_buffer), final)


def _grant(size: int) -> BufferGrant:
    """What the server's socket got: the same request from a process with its privileges."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        return request_buffer(sock, "receive", size)


def _phase(name: str, seconds: float, workers: list[Worker], server: Worker,
           probe: Any) -> Phase:
    for w in workers:
        w.send("phase", name=name)
    stats0 = probe.server_stats()
    for w in workers:
        w.mark_cpu()
    cpu0 = cpu_seconds(server.pid)
    wait0 = run_delay_s(server.pid)
    t0 = time.monotonic()
    rss = [rss_bytes(server.pid)]
    queued = [udp_queued(server.pid)]
    while (left := t0 + seconds - time.monotonic()) > 0:
        time.sleep(min(1.0, left))
        rss.append(rss_bytes(server.pid))
        queued.append(udp_queued(server.pid))
    cpu = cpu_seconds(server.pid) - cpu0
    clients_cpu = sum(w.cpu_since_mark() for w in workers)
    elapsed = time.monotonic() - t0
    wait = run_delay_s(server.pid) - wait0
    return Phase(name, elapsed, cpu, clients_cpu, wait, rss, stats0, probe.server_stats(),
                 queued=queued)


# -- report --------------------------------------------------------------------------------
def phase_row(phase: Phase) -> dict[str, float]:
    """The figures of one phase: rates, latency over sessions, server CPU and memory."""
    per = [s["phases"].get(phase.name) for s in phase.sessions]
    per_ok = [p for p in per if p]
    p50s = [p["p50"] for p in per_ok]
    p99s = [p["p99"] for p in per_ok]
    return {
        "offered": sum(p["sent"] / p["seconds"] for p in per_ok if p["seconds"] > 0),
        "delivered": sum(p["received"] / p["seconds"] for p in per_ok if p["seconds"] > 0),
        "p50": median(p50s),
        "p99": median(p99s),
        "p99_worst": max((v for v in p99s if not math.isnan(v)), default=math.nan),
        "cpu_pct": 100 * phase.cpu_s / phase.seconds,
        "clients_cpu_pct": 100 * phase.clients_cpu_s / phase.seconds,
        "wait_pct": 100 * phase.wait_s / phase.seconds,
        "rss0": phase.rss[0] / MiB,
        "rss1": phase.rss[-1] / MiB,
        "rss_max": max(phase.rss) / MiB,
        "server_in": phase.server_delta("values_in") / phase.seconds,
        "dropped": phase.server_delta("dropped"),
        "hop1_drops": phase.kernel.server,
        "queued_max": max(phase.queued, default=0) / MiB,
        # CPU the server spends per value it takes in and hands back out: the figure that
        # says what one core can carry, whatever share of it this machine gave the server.
        "cpu_us_per_value": phase.cpu_s * 1e6 / max(1, phase.server_delta("values_in")),
    }


def phase_table(r: Run) -> str:
    headers = ["phase", "s", "offered values/s", "delivered values/s", "server in values/s",
               "latency p50 µs (median session)", "p99 µs (median session)",
               "p99 µs (worst session)", "server dropped", "server CPU %",
               "server CPU µs per value (in + out)", "server waited for a CPU %",
               "clients CPU % (all processes)", "server RSS MiB start / max / end"]
    rows = []
    for ph in r.phases:
        x = phase_row(ph)
        rows.append([ph.name, fmt(ph.seconds, 1), fmt(x["offered"]), fmt(x["delivered"]),
                     fmt(x["server_in"]), fmt(x["p50"]), fmt(x["p99"]), fmt(x["p99_worst"]),
                     fmt(x["dropped"]), fmt(x["cpu_pct"]), fmt(x["cpu_us_per_value"], 1),
                     fmt(x["wait_pct"]),
                     fmt(x["clients_cpu_pct"]),
                     f"{x['rss0']:.1f} / {x['rss_max']:.1f} / {x['rss1']:.1f}"])
    return markdown_table(headers, rows)


def _last_stats(r: Run) -> Params:
    """The server's counters after the drain if the run has them, else after the last phase."""
    if r.final_stats is not None:
        return r.final_stats
    return r.phases[-1].stats1 if r.phases else {}


def first_hop_lost(r: Run) -> int:
    """Values that never reached the server (sequence gaps its publish channels counted).

    Only publish channels count: the server numbers nothing it receives on a subscription,
    so a subscribe channel reports ``lost`` as -1 ("measured by the client"), and summing
    those took one per subscription off the figure, down to below zero.
    """
    return sum(int(c["lost"]) for s in _last_stats(r).get("sessions", [])
               for c in s["channels"].values() if c.get("direction") == "publish")


def totals_line(r: Run) -> str:
    sent = sum(int(x["sent"]) for x in r.results)
    received = sum(int(x["received"]) for x in r.results)
    lost = sent - received
    pct = 100 * lost / sent if sent else 0.0
    when = ("once the clients had drained" if r.final_stats is not None
            else "by the end of the last phase")
    return (f"Whole run: {sent:,} values written, {received:,} delivered to the subscribing "
            f"channels, {lost:,} not delivered ({pct:.2f} %), of which {first_hop_lost(r):,} never "
            f"reached the server (its sequence gaps, {when}); gaps seen "
            f"by the clients "
            f"{sum(int(x['lost_seq']) for x in r.results):,}; session writes the clients "
            f"skipped (behind schedule) {r.skipped_ticks:,}.")


def clients_dropped(r: Run) -> int:
    """Values of the load clients' subscriptions the server dropped (not the slow consumer's)."""
    return sum(int(c.get("dropped", 0)) for s in _last_stats(r).get("sessions", [])
               if str(s.get("name", "")).startswith("load-") for c in s["channels"].values())


def loss_by_stage(r: Run) -> str:
    """The whole run's values stage by stage (:mod:`.load_stages`), and the server's buffer."""
    st = stages(r.results, first_hop_lost(r), clients_dropped(r),
                r.skipped_ticks * r.settings.channels, r.kernel)
    lines = [stage_table(st, sum(int(x.get("send_errors", 0)) for x in r.results))]
    if r.grant is not None:
        lines += ["", f"Server's {r.grant.describe()}; the kernel reports {r.grant.reported:,} "
                  "(it doubles the request for its bookkeeping; a 195-byte bundle of ten values "
                  "takes 832 bytes of it on loopback)."]
    return "\n".join(lines)


def describe(s: Settings) -> str:
    """How the clients were run, for the report."""
    who = ("protocol-level UDP sessions (`--client raw`, one thread per process)"
           if s.client == "raw" else f"SDK sessions (`--client sdk`, Bridge over {s.transport})")
    how = ("every channel of a session's tick in one datagram both ways (bundles)" if s.bundles
           else "one datagram per value both ways (`--no-bundles`)")
    if s.client_nice:
        how += f"; client processes at niceness +{s.client_nice} (the server at 0)"
    return (f"as {who} in {s.processes} client processes, one server process, loopback; "
            "each value goes client -> server -> client (the clients subscribe to their own "
            f"topics), {how}")


def report(r: Run, command: Sequence[str]) -> str:
    s = r.settings
    slow = next((p for p in r.phases if p.name == "slow"), None)
    lines = [report_header("Load: many clients on one server", command), "",
             f"{s.clients} sessions x {s.channels} channels at {s.rate_hz:g} Hz "
             f"(offered {s.offered:,.0f} values/s) {describe(s)}. Server `max_write_buffer` "
             f"{s.max_write_buffer >> 10} KiB; watchdog 500/5000 ms.", "",
             phase_table(r), "", totals_line(r), "", loss_by_stage(r), "",
             f"Load average before: {', '.join(f'{x:.2f}' for x in r.load_before)}; after: "
             f"{', '.join(f'{x:.2f}' for x in r.load_after)}."]
    if slow is not None:
        st = slow.named("slow-consumer")
        if st is not None:
            lines += ["", f"Slow consumer (subscribed over TCP to {s.slow_topics} of the "
                      f"clients' topics and to a bulk topic fed at {s.bulk_rate:,.0f} values/s "
                      f"in batches; never reads): {st['values_out']:,} values offered to it, "
                      f"{st['dropped']:,} dropped and counted, {st['tcp_queued_bytes']:,} bytes "
                      f"queued at the end of the phase (bound {s.max_write_buffer:,})."]
    return "\n".join(lines) + "\n"
