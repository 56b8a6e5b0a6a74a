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

import importlib
import math
import os
import subprocess
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Literal

from rlbridge.bench.common import (
    STARTUP_S,
    BenchError,
    Control,
    Link,
    Params,
    ProcessGroup,
    Role,
    Side,
    Tally,
    emit,
    flood,
    fmt,
    hold,
    markdown_table,
    median,
    paced,
    percentile,
    ratio,
    report_header,
    run_flow,
    start_server,
    wait_for_go,
)
from rlbridge.bench.throughput import _write_loop

MODULE = "rlbridge.bench.ros2"
MSG_TYPE = "std_msgs/msg/Float64"
DEPTH = 10
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


# -- worker roles (child processes) --------------------------------------------------------
@contextmanager
def _ros_node(name: str) -> Iterator[Any]:
    """A plain rclpy node with its executor spun in a thread: what a ROS user writes."""
    with warnings.catch_warnings():  # lark (under rosidl_generator_py) imports sre_parse
        warnings.simplefilter("ignore", DeprecationWarning)
        importlib.import_module("rosidl_generator_py")
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    context = Context()
    context.init(args=[])
    node = Node(name, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, name="bench-ros-spin", daemon=True)
    spinner.start()
    try:
        yield node
    finally:
        executor.shutdown(2.0)
        spinner.join(2.0)
        node.destroy_node()
        context.try_shutdown()


def _qos(reliability: str) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=DEPTH, durability=DurabilityPolicy.VOLATILE,
        reliability=(ReliabilityPolicy.BEST_EFFORT if reliability == "best_effort"
                     else ReliabilityPolicy.RELIABLE))


def _send(control: Control, params: Params, write: Callable[[float], object],
          write_flood: Callable[[], tuple[int, float]]) -> None:
    """The sender's part after set-up: warm up until ``go``, then pace or flood, report."""
    emit("ready")
    wait_for_go(control, lambda: write(-1.0))
    if params["mode"] == "latency":
        sent, t0, t1 = paced(lambda t: write(float(t)), float(params["rate_hz"]),
                             int(params["count"]))
    else:
        sent, t0 = write_flood()
        t1 = time.monotonic()
    emit("sent", sent=sent, t_start=t0, t_end=t1)
    hold(control)


def ros_publisher(params: Params) -> None:
    """An rclpy publisher node; ``rclpy.Publisher.publish`` per value."""
    control = Control()
    with _ros_node("rlbridge_bench_pub") as node:
        cls = importlib.import_module("std_msgs.msg").Float64
        pub = node.create_publisher(cls, params["topic"], _qos("reliable"))

        def write(value: float) -> None:
            pub.publish(cls(data=value))

        msg = cls(data=1.0)

        def write_flood() -> tuple[int, float]:
            sent, t0, _ = flood(lambda: pub.publish(msg), int(params["count"]),
                                float(params["seconds"]))
            return sent, t0

        _send(control, params, write, write_flood)


def sdk_publisher(params: Params) -> None:
    """An SDK publisher; ``write`` per value (flow-controlled by its ring in a flood)."""
    from rlbridge.csp.bridge import Bridge

    control = Control()
    buffer = 1 << 16
    bridge = Bridge.connect(params["host"], int(params["port"]), name="bench-ros2-pub",
                            nodelay=True)
    out = bridge.publish(params["topic"], MSG_TYPE, "data", transport=params["transport"],
                         buffer_size=buffer)

    def write_flood() -> tuple[int, float]:
        sent, t0 = _write_loop(out, 1, buffer // 2, int(params["count"]),
                               float(params["seconds"]), 0.0)
        bridge.send(wait=True)
        return sent, t0

    _send(control, params, out.write, write_flood)


def _receive(control: Control, params: Params, joined: threading.Event, tally: Tally) -> None:
    """The receiver's part after set-up: ``joined`` at the first warm-up, then the tally."""
    emit("ready")
    if not joined.wait(STARTUP_S):
        raise TimeoutError("no warm-up value arrived (discovery did not match the endpoints)")
    emit("joined")
    while not tally.done(time.monotonic()):
        time.sleep(0.005)
    tally.report()


def _on_value(value: float, joined: threading.Event, tally: Tally, latency: bool) -> None:
    if value < 0:
        joined.set()
    else:
        if latency:
            tally.samples.append(time.time_ns() - int(value))
        tally.add(1, time.monotonic())


def ros_subscriber(params: Params) -> None:
    """An rclpy subscriber node: one callback per message on the executor thread."""
    control = Control()
    tally = Tally(control, float(params["idle_s"]))
    joined = threading.Event()
    latency = params["mode"] == "latency"
    with _ros_node("rlbridge_bench_sub") as node:
        cls = importlib.import_module("std_msgs.msg").Float64
        node.create_subscription(cls, params["topic"],
                                 lambda msg: _on_value(msg.data, joined, tally, latency),
                                 _qos(params["reliability"]))
        _receive(control, params, joined, tally)


def sdk_subscriber(params: Params) -> None:
    """An SDK subscriber: blocking reads in a thread of its own, as a control loop would."""
    from rlbridge.csp.bridge import Bridge

    control = Control()
    tally = Tally(control, float(params["idle_s"]))
    joined = threading.Event()
    latency = params["mode"] == "latency"
    bridge = Bridge.connect(params["host"], int(params["port"]), name="bench-ros2-sub",
                            nodelay=True)
    ch = bridge.subscribe(params["topic"], MSG_TYPE, "data", transport=params["transport"],
                          blocking=True, buffer_size=1 << 16)
    stop = threading.Event()

    def read_loop() -> None:
        while not stop.is_set():
            try:
                values = [ch.read(0.05), *ch.read_many()]
            except TimeoutError:
                continue
            for value in values:
                _on_value(value, joined, tally, latency)

    reader = threading.Thread(target=read_loop, name="bench-ros2-read", daemon=True)
    reader.start()
    try:
        _receive(control, params, joined, tally)
    finally:
        stop.set()
        reader.join(1.0)


ROLES: dict[str, Role] = {"ros_publisher": ros_publisher, "sdk_publisher": sdk_publisher,
                          "ros_subscriber": ros_subscriber, "sdk_subscriber": sdk_subscriber}


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
    unknown = set(settings.only) - {c.key for c in CASES}
    if unknown:
        raise BenchError(f"unknown row key(s) {', '.join(sorted(unknown))}; the rows are "
                         f"{', '.join(c.key for c in CASES)}")
    scoped = RosScopedLink(link, ros_scope())
    selected = [c for c in CASES if not settings.only or c.key in settings.only]
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
