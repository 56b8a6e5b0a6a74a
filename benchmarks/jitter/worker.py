"""A ``python -m benchmarks.jitter run`` worker: one scenario in this process, lateness to JSON.

Also the GIL study's extra threads (pure-Python work, a ``sendto`` loop), the set-point
publisher process, and :func:`prepare_process`, the conditions every loop process gets.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import socket
import statistics
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchmarks.jitter.config import (
    F64,
    PROCESS_SUFFIX,
    TOPIC_IN,
    TOPIC_IN_FAST,
    TOPIC_OUT,
)
from rlbridge.csp import patterns
from rlbridge.csp.bridge import Bridge
from rlbridge.csp.gil import HRT_SWITCH_INTERVAL
from rlbridge.csp.isolated import IsolatedCoupling, Layout
from rlbridge.csp.rtenv import prepare_hrt_process, thread_scheduling


def prepare_process(mlock: bool) -> dict[str, Any]:
    """Give this loop process the conditions every measured process gets; say what held."""
    return dict(prepare_hrt_process(mlock))


def loop_options(args: argparse.Namespace) -> dict[str, Any]:
    """The coupling's loop options from a worker's command line."""
    # an explicit --switch-interval (the GIL study's conditions) wins over the loop's own
    held = None if args.switch_interval is not None else HRT_SWITCH_INTERVAL
    return {"period": args.period, "cycles": args.cycles, "priority": args.priority,
            "cpu": args.cpu, "switch_interval": held}


class FirstOrderFilter:
    """The receive patterns' control law: a first-order filter, a tiny controller.

    A module-level class, so that it can cross to a loop in its own process (pickled).
    """

    def __init__(self) -> None:
        self.state = 0.0

    def __call__(self, value: Any) -> None:
        self.state += 0.1 * (float(value) - self.state)


class Sine:
    """The send patterns' control law: a sine, one sample per release (picklable)."""

    def __init__(self) -> None:
        self.k = 0

    def __call__(self) -> float:
        self.k += 1
        return math.sin(self.k * 0.001)


def receive_law() -> Callable[[Any], None]:
    return FirstOrderFilter()


def send_law() -> Callable[[], float]:
    return Sine()


def wait_first_value(channel: Any, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while channel.statistics().written == 0:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def _watchdog(coupling: Any, done: threading.Event, seconds: float,
              info: dict[str, Any]) -> None:
    """End a run that outlives its deadlines (a naive receive whose messages stopped).

    Blocked in ``Event.wait`` (C, no GIL) for the whole run, so it costs the loop nothing.
    """
    if not done.wait(seconds):
        info["stalled"] = True
        coupling.stop()


def probed(fn: Callable[..., Any], info: dict[str, Any]) -> Callable[..., Any]:
    """Wrap a control law so that its first call records the HRT thread's scheduling."""

    def probe(*args: Any) -> Any:
        if "policy" not in info:
            info.update(thread_scheduling())  # what the loop runs with, from inside it
        return fn(*args)

    return probe


_RATES = {"send-loop-100": 100.0, "send-loop-1000": 1000.0, "sdk-100": 100.0,
          "sdk-1000": 1000.0, "sdk-1000-rtio": 1000.0}
_NO_BRIDGE = ("reference", "pyburn", "sendto-1000")


def _coupling(name: str, bridge: Bridge | None, info: dict[str, Any],
              loop: dict[str, Any]) -> patterns.BaseCoupling:
    """The scenario's coupling: a pattern of :mod:`rlbridge.csp.patterns` or a GIL condition.

    A ``-process`` scenario is the pattern's default layout (the loop in its own process,
    which records its own scheduling); the others run in-process with probed laws.
    """
    base, process = name.removesuffix(PROCESS_SUFFIX), name.endswith(PROCESS_SUFFIX)
    layout: Layout = "process" if process else "thread"
    recv: Callable[[Any], None] = receive_law() if process else probed(receive_law(), info)
    send: Callable[[], float] = send_law() if process else probed(send_law(), info)
    if bridge is None:
        return patterns.reference(lambda: recv(send()), **loop)
    if base.startswith("sdk-"):
        return _sdk_coupling(bridge, TOPIC_IN if name == "sdk-100" else TOPIC_IN_FAST,
                             recv, send, loop)
    if base in ("receive-nonblocking", "receive-blocking"):
        receive = (patterns.receive_nonblocking if base == "receive-nonblocking"
                   else patterns.receive_blocking)
        return receive(bridge, TOPIC_IN, F64, recv, layout=layout, **loop)
    if base == "receive-naive":
        return patterns.receive_naive(bridge, TOPIC_IN, F64, recv, **loop)
    if base == "send-naive":
        return patterns.send_naive(bridge, TOPIC_OUT, F64, send, **loop)
    if base == "send-buffered":
        return patterns.send_buffered(bridge, TOPIC_OUT, F64, send, layout=layout, **loop)
    if base == "send-sampled":
        return patterns.send_sampled(bridge, TOPIC_OUT, F64, send, layout=layout, **loop)
    if base in ("send-loop-100", "send-loop-1000"):
        return patterns.send_loop(bridge, TOPIC_OUT, F64, send, layout=layout, **loop)
    raise SystemExit(f"unknown scenario {name!r}")


def _extra_threads(name: str, stop: threading.Event) -> list[threading.Thread]:
    """The GIL study's competitors of the loop in its own interpreter."""
    if name == "pyburn":
        return [threading.Thread(target=_pyburn, args=(stop,), name="pyburn")]
    if name == "sendto-1000":
        return [threading.Thread(target=_sendto, args=(stop, 1000.0), name="sendto")]
    return []


def worker_main(args: argparse.Namespace) -> None:
    """Run one scenario in this process and write its lateness samples as JSON.

    The ``shm-*`` scenarios are not run here but by :func:`benchmarks.jitter.shm.shm_parent`
    (the worker's entry in :mod:`.cli` picks); this module knows nothing of them.
    """
    name: str = args.scenario
    info = prepare_process(args.mlock)
    stop = threading.Event()
    extra = _extra_threads(name, stop)
    bridge: Bridge | None = None
    try:
        if name not in _NO_BRIDGE:
            bridge = Bridge.connect("127.0.0.1", args.port, nodelay=True,
                                    send_rate_hz=_RATES.get(name.removesuffix(PROCESS_SUFFIX)),
                                    name=f"bench-{name}")  # the loop holds its own interval
        if name == "sdk-1000-rtio" and bridge is not None:
            info["io_threads"] = "SCHED_FIFO 40" if bridge.set_io_priority(40) else "refused"
        coupling = _coupling(name, bridge, info, loop_options(args))
        incoming = coupling.channels.get("in")
        if incoming is not None and not wait_first_value(incoming):
            raise SystemExit(f"no value arrived on {TOPIC_IN} within 5 s: is the publisher up?")
        result = run_measured(coupling, name, info, stop, extra,
                              args.cycles * args.period + 15.0, cpu=args.cpu)
    finally:
        stop.set()
        for thread in extra:
            thread.join(5.0)
        if bridge is not None:
            bridge.close()
    Path(args.result).write_text(json.dumps(result))


def run_measured(coupling: patterns.BaseCoupling, name: str, info: dict[str, Any],
                 stop: threading.Event, extra: list[threading.Thread],
                 limit: float, cpu: int | None = None) -> dict[str, Any]:
    """Run the coupling next to ``extra`` threads and a watchdog; the worker's JSON result.

    Also records how much time the hypervisor stole from the loop's CPU (``cpu``; all CPUs
    when the loop is not pinned) while the loop ran: on a VM that, not our code, is what
    most often makes one run's p99 ten times another's.
    """
    extra.append(threading.Thread(target=_watchdog, args=(coupling, stop, limit, info),
                                  name="watchdog"))
    for thread in extra:
        thread.start()
    clocks = _thread_clocks()
    stolen = cpu_steal_ticks(cpu)
    wall = time.monotonic()
    coupling.run()
    wall = time.monotonic() - wall
    after = cpu_steal_ticks(cpu)
    if stolen is not None and after is not None:
        info["steal_ms"] = round((after - stolen) * 1000 / _CLOCK_TICKS, 1)
    info["thread_cpu_percent"] = {
        thread: round(100 * (time.clock_gettime(clock) - t0) / wall, 2)
        for thread, (clock, t0) in clocks.items()}
    info.update(_channel_info(coupling))
    if isinstance(coupling, IsolatedCoupling):
        info.update(coupling.loop_info)  # recorded inside the loop's own process
    return {"scenario": name, "lateness_ns": coupling.lateness_ns(),
            "missed": coupling.stats().missed, "released": coupling.released, "info": info}


_CLOCK_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def cpu_steal_ticks(cpu: int | None) -> int | None:
    """The ``steal`` counter of /proc/stat for ``cpu`` (None: all CPUs); None where absent."""
    label = "cpu" if cpu is None else f"cpu{cpu}"
    try:
        with open("/proc/stat") as stat:
            for line in stat:
                fields = line.split()
                if fields and fields[0] == label:
                    return int(fields[8]) if len(fields) > 8 else None
    except OSError:
        return None
    return None


def _thread_clocks() -> dict[str, tuple[int, float]]:
    """CPU-time clocks of the SDK's threads (and the study's extra threads), with a start."""
    out: dict[str, tuple[int, float]] = {}
    for thread in threading.enumerate():
        if thread.ident is None or thread.name not in (
                "rlbridge-recv", "rlbridge-send", "pyburn", "sendto"):
            continue
        with contextlib.suppress(OSError):
            clock = time.pthread_getcpuclockid(thread.ident)
            out[thread.name] = (clock, time.clock_gettime(clock))
    return out


def _channel_info(coupling: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for role, channel in coupling.channels.items():
        stats = channel.statistics()
        out[role] = {"written": stats.written, "read": stats.read,
                     "overwritten": stats.overwritten,
                     "hrt_blocking_reads": stats.hrt_blocking_reads}
    return out


def _sdk_coupling(bridge: Bridge, topic: str, recv: Callable[[Any], None],
                  send: Callable[[], float], loop: dict[str, Any]) -> patterns.Coupling:
    """GIL study: the loop reads a non-blocking input and writes a send-loop output."""
    incoming = bridge.subscribe(topic, F64, blocking=False, buffer_size=1, initial=0.0)
    out = bridge.publish(TOPIC_OUT, F64, through_buffer=True)

    def body() -> None:
        recv(incoming.read())
        out.write(send())

    return patterns.Coupling("sdk", body, channels={"in": incoming, "out": out},
                             closers=[incoming.close], **loop)


def _pyburn(stop: threading.Event) -> None:
    """Pure-Python work until stopped: holds the GIL except at forced switches."""
    while not stop.is_set():
        total = 0
        for i in range(10_000):
            total += i * i


def _sendto(stop: threading.Event, rate: float) -> None:
    """``sendto`` of 64 bytes at ``rate``: mostly blocked in C, holding no GIL."""
    from rlbridge.csp.timer import PeriodicTimer

    timer = PeriodicTimer(1.0 / rate, history=1)
    payload = bytes(64)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sink = ("127.0.0.1", 9)  # discard; unconnected UDP never reports the ICMP error
        while timer.wait_next(stop):
            with contextlib.suppress(OSError):
                sock.sendto(payload, sink)




def publisher_main(args: argparse.Namespace) -> None:
    """Publish a sine on ``--topic`` at ``--rate`` for ``--seconds`` (a separate process)."""
    from rlbridge.csp.timer import PeriodicTimer
    from rlbridge.wire.link import LinkState

    timer = PeriodicTimer(1.0 / args.rate, history=1)
    end = time.monotonic() + args.seconds
    k = 0
    while time.monotonic() < end:  # reconnect if the server dropped the session
        with Bridge.connect(args.host, args.port, nodelay=True,
                            name="bench-publisher") as bridge:
            out = bridge.publish(args.topic, F64, transport="udp")
            while time.monotonic() < end and bridge.link_state is not LinkState.LOST:
                timer.wait_next()
                k += 1
                out.write(math.sin(k / args.rate))
        print(f"publisher: session lost after {k} values; reconnecting", flush=True)




def switch_cost(intervals: tuple[float, ...] = (0.005, 0.0005, 0.0001), work: int = 2_000_000,
                repeats: int = 5) -> str:
    """The other side of a short switch interval: two computing threads, forced hand-overs.

    Wall time for two threads that each run ``work`` iterations of pure Python, per switch
    interval, interleaved over ``repeats`` rounds; markdown with the median and the ratio to
    the first interval. This is what an application's CPU-bound threads pay while an HRT loop
    holds a shorter interval.
    """
    def burn() -> None:
        total = 0
        for i in range(work):
            total += i * i

    before = sys.getswitchinterval()
    times: dict[float, list[float]] = {s: [] for s in intervals}
    try:
        for _ in range(repeats):
            for seconds in intervals:
                sys.setswitchinterval(seconds)
                threads = [threading.Thread(target=burn) for _ in range(2)]
                t0 = time.perf_counter()
                for thread in threads:
                    thread.start()
                for thread in threads:
                    thread.join()
                times[seconds].append(time.perf_counter() - t0)
    finally:
        sys.setswitchinterval(before)
    base = statistics.median(times[intervals[0]])
    rows = ["| switch interval | wall time, 2 threads x "
            f"{work:,} iterations (median of {repeats}) | ratio |", "|---|---:|---:|"]
    for seconds, values in times.items():
        median = statistics.median(values)
        rows.append(f"| {seconds * 1e6:g} us | {median * 1e3:.0f} ms | {median / base:.3f} |")
    return "\n".join(rows)
