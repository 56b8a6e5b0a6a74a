"""The child side of a benchmark: its entry point, its commands from the parent, its pacing.

A child reads commands from its stdin (JSON lines, :class:`Control`) and reports on stdout
(:func:`emit`). It is bounded two ways of its own, besides the parent stopping it, so a failed
run never leaves a busy process behind: it exits when its stdin reaches EOF (the parent died),
and after a hard lifetime it is given at spawn (:func:`worker_main`).
"""

from __future__ import annotations

import importlib
import json
import os
import sys
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from rlbridge.bench.base import Params, Role

#: Modules whose ``ROLES`` a child may run (the child's entry point refuses anything else).
WORKER_MODULES = ("rlbridge.bench.child", "rlbridge.bench.throughput",
                  "rlbridge.bench.latency", "rlbridge.bench.latency_stages",
                  "rlbridge.bench.baselines",
                  "rlbridge.bench.ros2_roles", "rlbridge.bench.netpath",
                  "rlbridge.bench.load_roles", "rlbridge.bench.cpu",
                  "rlbridge.bench.feedback")


def emit(event: str, **fields: Any) -> None:
    """Report to the parent: one JSON line on stdout."""
    sys.stdout.write(json.dumps({"event": event, **fields}) + "\n")
    sys.stdout.flush()


class Control:
    """A child's commands from the parent, read by a thread; EOF on stdin ends the process."""

    def __init__(self, on_eof: Callable[[], None] | None = None) -> None:
        self._cond = threading.Condition()
        self._msgs: list[Params] = []
        self._on_eof = on_eof
        threading.Thread(target=self._read, name="bench-control", daemon=True).start()

    def _read(self) -> None:
        for line in sys.stdin.buffer:
            with self._cond:
                self._msgs.append(json.loads(line))
                self._cond.notify_all()
        if self._on_eof is not None:
            self._on_eof()
        else:
            os._exit(0)

    def poll(self, cmd: str) -> Params | None:
        """The first pending ``cmd`` message, without waiting."""
        with self._cond:
            for i, msg in enumerate(self._msgs):
                if msg.get("cmd") == cmd:
                    return self._msgs.pop(i)
        return None

    def wait(self, cmd: str, timeout: float = 60.0) -> Params:
        """The next ``cmd`` message; checked and waited for under one lock (no lost wake-up)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                msg = self.poll(cmd)  # the condition's lock is re-entrant
                if msg is not None:
                    return msg
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no '{cmd}' from the parent within {timeout} s")
                self._cond.wait(left)


class Tally:
    """A receiver's counts and the stop rule every receiver shares.

    The receiver does not know how many values to expect until the sender has finished; the
    parent then sends ``expect``. From that moment the receiver stops as soon as it has them
    all, or once nothing arrived for ``idle_s`` (what is missing then was lost, and counted).
    ``t_last`` is the arrival time of the last value, so the idle wait is not measured.
    """

    def __init__(self, control: Control, idle_s: float) -> None:
        self.control = control
        self.idle_s = idle_s
        self.received = 0
        self.t_first = 0.0
        self.t_last = 0.0
        self.samples: list[int] = []
        self._expected: int | None = None
        self._expect_at = 0.0

    def add(self, n: int, now: float) -> None:
        """Count ``n`` values that arrived at ``now``."""
        if n:
            if not self.received:
                self.t_first = now
            self.received += n
            self.t_last = now

    def done(self, now: float) -> bool:
        """True once every expected value arrived, or the idle wait after ``expect`` ran out."""
        if self._expected is None:
            msg = self.control.poll("expect")
            if msg is None:
                return False
            self._expected, self._expect_at = int(msg["count"]), now
        if self.received >= self._expected:
            return True
        return now - max(self.t_last, self._expect_at) > self.idle_s

    def report(self, **extra: Any) -> None:
        """Send the counts (and ``extra``) to the parent as the ``result`` event."""
        emit("result", received=self.received, t_first=self.t_first, t_last=self.t_last,
             samples=self.samples, **extra)


def flood(send: Callable[[], object], count: int, seconds: float) -> tuple[int, float, float]:
    """Call ``send`` as fast as possible, ``count`` times or for ``seconds``, whichever first.

    The clock is read once per 256 calls so that the loop measures the transport, not us.
    """
    sent = 0
    start = time.monotonic()
    end = start + seconds
    while sent < count:
        n = min(256, count - sent)
        for _ in range(n):
            send()
        sent += n
        if time.monotonic() >= end:
            break
    return sent, start, time.monotonic()


def paced(send: Callable[[int], object], rate_hz: float, count: int) -> tuple[int, float, float]:
    """Call ``send(time.time_ns())`` ``count`` times at ``rate_hz`` on an absolute schedule.

    A late call is not followed by a burst: the schedule is kept, so one stall costs one
    sample's latency, not a queue of them.
    """
    period = 1.0 / rate_hz
    start = time.monotonic()
    for i in range(count):
        delay = start + i * period - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        send(time.time_ns())
    return count, start, time.monotonic()


def wait_for_go(control: Control, warmup: Callable[[], object] | None = None) -> None:
    """Wait for ``go``; meanwhile call ``warmup`` every 10 ms (slow-joiner pub/sub)."""
    while True:
        try:
            control.wait("go", 0.01)
            return
        except TimeoutError:
            if warmup is not None:
                warmup()


def hold(control: Control) -> None:
    """Keep a sender alive (its queues may still drain) until the parent closes stdin."""
    control.wait("never", 1e9)


def worker_main() -> None:
    """Entry point of a child: ``<module> <role> <json params> <lifetime s>``."""
    module, role, params, lifetime = sys.argv[1:5]
    if module not in WORKER_MODULES:
        raise SystemExit(f"not a benchmark module: {module}")
    timer = threading.Timer(float(lifetime), lambda: os._exit(4))
    timer.daemon = True
    timer.start()
    roles: Mapping[str, Role] = importlib.import_module(module).ROLES
    try:
        roles[role](json.loads(params))
    except Exception as exc:
        emit("error", message=f"{type(exc).__name__}: {exc}")
        raise
    sys.stdout.flush()
    os._exit(0)  # do not wait for daemon threads of SDKs that are still winding down


def server_role(params: Params) -> None:
    """A bridge server (the same ``Server.serve`` the CLI runs); stops when stdin closes."""
    import logging

    from rlbridge.server import Server, ServerConfig, new_event_loop
    from rlbridge.server.runner import run_on_loop

    logging.basicConfig(level=params.get("log_level", "INFO"), stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    # An emulated link between network namespaces: nothing else can reach it (insecure=True).
    config = ServerConfig(host=params["host"], port=0,
                          **{"insecure": True, **params.get("config", {})})
    server = Server(config)
    Control(on_eof=server.stop)
    run_on_loop(server.serve(install_signal_handlers=True,
                             started=lambda a: emit("ready", port=a.port)),
                lambda: new_event_loop(config.use_uvloop))


ROLES: dict[str, Role] = {"server": server_role}
