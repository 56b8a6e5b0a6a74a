"""A ``rlbridge bench jitter`` worker: one scenario in this process, lateness to JSON.

Also the GIL study's extra threads (pure-Python work, a ``sendto`` loop), the set-point
publisher process, and :func:`prepare_process`, the conditions every loop process gets.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import ctypes.util
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

from rlbridge.bench.jitter_config import F64, TOPIC_IN, TOPIC_IN_FAST, TOPIC_OUT
from rlbridge.csp import patterns
from rlbridge.csp.bridge import Bridge
from rlbridge.csp.gil import HRT_SWITCH_INTERVAL

_MCL_CURRENT, _MCL_FUTURE = 1, 2
_PR_SET_TIMERSLACK = 29


def prepare_process(mlock: bool) -> dict[str, Any]:
    """Give this loop process the conditions every measured process gets; say what held.

    ``mlockall`` keeps the loop's pages resident (no page fault on a cold page mid-cycle);
    a timer slack of 1 ns stops the kernel from coalescing the loop's wake-up with others
    (real-time threads get no slack anyway; this covers a run without ``--rt``).
    """
    info: dict[str, Any] = {}
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    if mlock:
        ok = libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0
        info["mlockall"] = "yes" if ok else f"refused ({os.strerror(ctypes.get_errno())})"
    info["timer_slack"] = "1 ns" if libc.prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0) == 0 else \
        "default"
    return info


def loop_options(args: argparse.Namespace) -> dict[str, Any]:
    """The coupling's loop options from a worker's command line."""
    # an explicit --switch-interval (the GIL study's conditions) wins over the loop's own
    held = None if args.switch_interval is not None else HRT_SWITCH_INTERVAL
    return {"period": args.period, "cycles": args.cycles, "priority": args.priority,
            "cpu": args.cpu, "switch_interval": held}


def receive_law() -> Callable[[Any], None]:
    state = [0.0]

    def law(value: Any) -> None:
        state[0] += 0.1 * (float(value) - state[0])  # a first-order filter: a tiny controller

    return law


def send_law() -> Callable[[], float]:
    k = [0]

    def law() -> float:
        k[0] += 1
        return math.sin(k[0] * 0.001)

    return law


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


def _policy() -> str:
    """Scheduling policy of the calling thread (recorded from inside the HRT loop)."""
    try:
        policy = os.sched_getscheduler(0)
        prio = os.sched_getparam(0).sched_priority
    except (AttributeError, OSError):
        return "unknown"
    names = {os.SCHED_OTHER: "SCHED_OTHER", os.SCHED_FIFO: "SCHED_FIFO",
             os.SCHED_RR: "SCHED_RR"}
    if policy == os.SCHED_OTHER:
        return f"SCHED_OTHER nice {os.getpriority(os.PRIO_PROCESS, 0)}"
    return f"{names.get(policy, str(policy))} {prio}"


def probed(fn: Callable[..., Any], info: dict[str, Any]) -> Callable[..., Any]:
    """Wrap a control law so that its first call records the HRT thread's scheduling."""

    def probe(*args: Any) -> Any:
        if "policy" not in info:
            info["policy"] = _policy()
            info["switch_interval"] = sys.getswitchinterval()  # what the loop runs with
            cpus = sorted(os.sched_getaffinity(0))
            info["cpus"] = "any" if len(cpus) == os.cpu_count() else ",".join(map(str, cpus))
        return fn(*args)

    return probe


_RATES = {"send-loop-100": 100.0, "send-loop-1000": 1000.0, "sdk-100": 100.0,
          "sdk-1000": 1000.0, "sdk-1000-rtio": 1000.0}
_NO_BRIDGE = ("reference", "pyburn", "sendto-1000")


def _coupling(name: str, bridge: Bridge | None, recv: Callable[[Any], None],
              send: Callable[[], float], loop: dict[str, Any]) -> patterns.Coupling:
    """The scenario's coupling: a pattern of :mod:`rlbridge.csp.patterns` or a GIL condition."""
    if bridge is None:
        return patterns.reference(lambda: recv(send()), **loop)
    receive = {"receive-nonblocking": patterns.receive_nonblocking,
               "receive-blocking": patterns.receive_blocking,
               "receive-naive": patterns.receive_naive}.get(name)
    if receive is not None:
        return receive(bridge, TOPIC_IN, F64, recv, **loop)
    send_pattern = {"send-naive": patterns.send_naive, "send-buffered": patterns.send_buffered,
                    "send-sampled": patterns.send_sampled, "send-loop-100": patterns.send_loop,
                    "send-loop-1000": patterns.send_loop}.get(name)
    if send_pattern is not None:
        return send_pattern(bridge, TOPIC_OUT, F64, send, **loop)
    if name.startswith("sdk-"):
        return _sdk_coupling(bridge, TOPIC_IN if name == "sdk-100" else TOPIC_IN_FAST,
                             recv, send, loop)
    raise SystemExit(f"unknown scenario {name!r}")


def _extra_threads(name: str, stop: threading.Event) -> list[threading.Thread]:
    """The GIL study's competitors of the loop in its own interpreter."""
    if name == "pyburn":
        return [threading.Thread(target=_pyburn, args=(stop,), name="pyburn")]
    if name == "sendto-1000":
        return [threading.Thread(target=_sendto, args=(stop, 1000.0), name="sendto")]
    return []


def worker_main(args: argparse.Namespace) -> None:
    """Run one scenario in this process and write its lateness samples as JSON."""
    if args.switch_interval is not None:
        sys.setswitchinterval(args.switch_interval)
    name: str = args.scenario
    if name.startswith("shm-"):
        from rlbridge.bench.jitter_shm import shm_parent

        Path(args.result).write_text(json.dumps(shm_parent(args)))
        return
    info = prepare_process(args.mlock)
    stop = threading.Event()
    extra = _extra_threads(name, stop)
    bridge: Bridge | None = None
    try:
        if name not in _NO_BRIDGE:
            bridge = Bridge.connect("127.0.0.1", args.port, nodelay=True,
                                    send_rate_hz=_RATES.get(name), name=f"bench-{name}",
                                    switch_interval=None)  # the loop holds its own
        if name == "sdk-1000-rtio" and bridge is not None:
            info["io_threads"] = "SCHED_FIFO 40" if bridge.set_io_priority(40) else "refused"
        coupling = _coupling(name, bridge, probed(receive_law(), info),
                             probed(send_law(), info), loop_options(args))
        incoming = coupling.channels.get("in")
        if incoming is not None and not wait_first_value(incoming):
            raise SystemExit(f"no value arrived on {TOPIC_IN} within 5 s: is the publisher up?")
        result = run_measured(coupling, name, info, stop, extra,
                              args.cycles * args.period + 15.0)
    finally:
        stop.set()
        for thread in extra:
            thread.join(5.0)
        if bridge is not None:
            bridge.close()
    Path(args.result).write_text(json.dumps(result))


def run_measured(coupling: patterns.Coupling, name: str, info: dict[str, Any],
                 stop: threading.Event, extra: list[threading.Thread],
                 limit: float) -> dict[str, Any]:
    """Run the coupling next to ``extra`` threads and a watchdog; the worker's JSON result."""
    extra.append(threading.Thread(target=_watchdog, args=(coupling, stop, limit, info),
                                  name="watchdog"))
    for thread in extra:
        thread.start()
    clocks = _thread_clocks()
    wall = time.monotonic()
    coupling.run()
    wall = time.monotonic() - wall
    info["thread_cpu_percent"] = {
        thread: round(100 * (time.clock_gettime(clock) - t0) / wall, 2)
        for thread, (clock, t0) in clocks.items()}
    info.update(_channel_info(coupling))
    loop = coupling.loop
    return {"scenario": name, "lateness_ns": loop.lateness_ns(),
            "missed": loop.stats().missed, "released": loop.released, "info": info}


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
