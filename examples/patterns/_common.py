"""Shared plumbing of the pattern examples: arguments, a publisher process, a summary line.

Start a server first (``rlbridge serve``), then run any example with ``--host/--port``. The
receive examples need someone publishing ``/example/setpoint``; ``--publish`` (on by default)
starts one in a *separate process* (so it does not share this interpreter's GIL) for as long as
the example runs, and stops it at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from rlbridge import DEFAULT_LAYOUT, BaseCoupling, Bridge, IsolatedCoupling, LoopOptions

F64 = "std_msgs/msg/Float64"
SETPOINT = "/example/setpoint"
OUTPUT = "/example/output"


def parser(description: str, *, layouts: bool = True) -> argparse.ArgumentParser:
    """The arguments every example takes (``--layout`` where the pattern has both)."""
    p = argparse.ArgumentParser(description=description,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--host", default="127.0.0.1", help="bridge server address")
    p.add_argument("--port", type=int, default=7411, help="bridge server port")
    p.add_argument("--cycles", type=int, default=2000, help="loop deadlines to run (bounded)")
    p.add_argument("--period-us", type=int, default=1000, help="loop period")
    if layouts:
        p.add_argument("--layout", choices=["process", "thread"], default=DEFAULT_LAYOUT,
                       help="the loop in its own process (default) or a thread of this one")
    return p


_PUBLISHER = Path(__file__).resolve().with_name("_publisher.py")
"""The publisher process's script, beside this one: the examples need only the package."""


@contextlib.contextmanager
def publisher(host: str, port: int, seconds: float, enabled: bool = True,
              rate: float = 100.0) -> Iterator[None]:
    """A sine on SETPOINT at ``rate`` from a separate process, killed on exit.

    The process is ``_publisher.py`` beside this file, run by this interpreter: nothing from
    a checkout (the examples run after ``pip install rlbridge-sdk``).
    """
    if not enabled:
        yield
        return
    proc = subprocess.Popen(
        [sys.executable, str(_PUBLISHER), "--host", host, "--port", str(port),
         "--topic", SETPOINT, "--rate", str(rate), "--seconds", str(seconds)],
        start_new_session=True)
    try:
        yield
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(10)


class Sine:
    """The value an example's HRT loop computes each cycle: a sine of the loop's own time.

    A module-level class, so that it can cross to a loop in its own process.
    """

    def __init__(self, period_us: int) -> None:
        self.period_s = period_us / 1e6
        self.k = 0

    def __call__(self) -> float:
        self.k += 1
        return math.sin(self.k * self.period_s)


def report(coupling: BaseCoupling) -> None:
    """One line of what the loop saw, where it ran, then the channels' counters."""
    stats = coupling.stats()
    print(f"{coupling.name}: {coupling.released} releases, {stats.missed} missed; "
          f"lateness p50 {stats.p50_ns / 1e3:.0f} us, p99 {stats.p99_ns / 1e3:.0f} us, "
          f"max {stats.max_ns / 1e3:.0f} us")
    if isinstance(coupling, IsolatedCoupling):
        info = coupling.loop_info
        print(f"  loop process: {info.get('policy')}, mlockall {info.get('mlockall')}, "
              f"ring dropped {info.get('ring_dropped')}")
    for role, channel in coupling.channels.items():
        print(f"  {role}: {channel.statistics()}")


def run(args: argparse.Namespace, make: Callable[[Bridge, LoopOptions], BaseCoupling], *,
        publish: bool = False, send_rate_hz: float | None = None) -> BaseCoupling:
    """Connect, build the example's coupling with ``make(bridge, loop_options)``, run, report.

    ``publish`` starts the SETPOINT publisher process first (the receive examples).
    Returns the finished coupling (``final_control`` is the law as a loop process left it).
    """
    loop: LoopOptions = {"period": args.period_us / 1e6, "cycles": args.cycles}
    seconds = args.cycles * args.period_us / 1e6 + 5
    with publisher(args.host, args.port, seconds, publish), \
            Bridge.connect(args.host, args.port, nodelay=True,
                           send_rate_hz=send_rate_hz) as bridge:
        if publish:
            wait_for_publisher(bridge)
        coupling = make(bridge, loop)
        coupling.run()
        report(coupling)
    return coupling


def wait_for_publisher(bridge: Bridge, timeout: float = 30.0) -> None:
    """Block (here, before any HRT loop runs) until SETPOINT carries a value.

    The publisher is a fresh process; without this a short run could end before it speaks.
    """
    probe = bridge.subscribe(SETPOINT, F64, blocking=True, buffer_size=1)
    try:
        probe.read(timeout=timeout)
    finally:
        bridge.unsubscribe(probe)


def final_law(coupling: BaseCoupling, local: Any) -> Any:
    """The control law after the run: the loop process's copy, or ``local`` in-process."""
    return coupling.final_control if isinstance(coupling, IsolatedCoupling) else local


def ignore(value: Any) -> None:
    """A control law that uses nothing (the naive receive example only shows the timing)."""
    del value
