"""What every benchmark shares: links, worker processes, CPU accounting, statistics, reports.

Every measured party runs in its own process, as it would in deployment: a publisher, a
server, a subscriber (or a baseline's sender and receiver). The parent only coordinates them
over pipes (JSON lines on each child's stdin and stdout) and sleeps in ``select`` while they
run, so it does not steal one of the machine's cores from what it measures.

A :class:`Link` decides where a process runs and which address reaches it. The default
:class:`LoopbackLink` runs everything here on 127.0.0.1; a link backed by the network emulator
(``rlbridge.netem``) can run side ``"a"`` (servers, receivers, listeners) and side ``"b"``
(clients, senders) in two namespaces without the benchmarks changing.

Children are bounded three ways, so a failed run never leaves a busy process behind: the parent
terminates (then kills) every child it spawned when the run ends, also on an exception; a child
exits on its own when its stdin reaches EOF (the parent died); and a child exits after a hard
lifetime it is given at spawn.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.metadata
import json
import math
import os
import platform
import select
import shlex
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any, Literal, Protocol

Side = Literal["a", "b"]
Params = dict[str, Any]
Role = Callable[[Params], None]

#: Modules whose ``ROLES`` a child may run (the child's entry point refuses anything else).
WORKER_MODULES = ("rlbridge.bench.common", "rlbridge.bench.throughput",
                  "rlbridge.bench.latency", "rlbridge.bench.baselines",
                  "rlbridge.bench.ros2_roles", "rlbridge.bench.netpath")
CLK_TCK = os.sysconf("SC_CLK_TCK")
#: Seconds a worker may take to start and report ``ready`` (imports on a loaded machine).
STARTUP_S = 30.0


class BenchError(RuntimeError):
    """A benchmark run failed (a child died, timed out, or reported an error)."""


class Skipped(Exception):
    """A row cannot be measured here (an optional package is missing); the reason is printed."""


# -- links ---------------------------------------------------------------------------------
class Link(Protocol):
    """Where benchmark processes run and how they reach each other.

    Side ``"a"`` hosts listeners (the bridge server, baseline receivers), side ``"b"`` the
    clients and senders; ``address(side)`` is the address a process on the other side uses.
    """

    name: str

    def address(self, side: Side) -> str: ...

    def popen(self, side: Side, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[bytes]:
        ...


class LoopbackLink:
    """Both sides on this machine, over 127.0.0.1."""

    name = "loopback"

    def address(self, side: Side) -> str:
        return "127.0.0.1"

    def popen(self, side: Side, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[bytes]:
        return subprocess.Popen(list(argv), **kwargs)


# -- parent side: workers ------------------------------------------------------------------
def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a live process, all threads (``/proc/<pid>/stat``)."""
    with open(f"/proc/{pid}/stat", "rb") as f:
        data = f.read()
    fields = data[data.rindex(b")") + 2 :].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


class Worker:
    """One child process speaking JSON lines; see the module docstring."""

    def __init__(self, name: str, proc: subprocess.Popen[bytes], stderr: IO[bytes]) -> None:
        self.name = name
        self.proc = proc
        self._stderr = stderr
        self._buf = bytearray()
        self._cpu0 = 0.0

    @property
    def pid(self) -> int:
        return self.proc.pid

    def send(self, cmd: str, **fields: Any) -> None:
        """Write one command line to the child's stdin."""
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write(json.dumps({"cmd": cmd, **fields}).encode() + b"\n")
            self.proc.stdin.flush()
        except BrokenPipeError:
            raise BenchError(f"{self.name} exited early{self.stderr_tail()}") from None

    def expect(self, event: str, timeout: float) -> Params:
        """Wait for the child's next ``event`` line; raise with its stderr if it fails."""
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        deadline = time.monotonic() + timeout
        while True:
            nl = self._buf.find(b"\n")
            if nl >= 0:
                line = bytes(self._buf[:nl])
                del self._buf[: nl + 1]
                msg: Params = json.loads(line)
                if msg.get("event") == event:
                    return msg
                if msg.get("event") == "error":
                    raise BenchError(f"{self.name}: {msg.get('message')}")
                continue
            left = deadline - time.monotonic()
            if left <= 0:
                raise BenchError(f"{self.name}: no '{event}' within {timeout:.1f} s"
                                 f"{self.stderr_tail()}")
            ready, _, _ = select.select([fd], [], [], left)
            if ready:
                chunk = os.read(fd, 65536)
                if not chunk:
                    self.proc.wait(2.0)
                    raise BenchError(f"{self.name} exited with {self.proc.returncode} before "
                                     f"'{event}'{self.stderr_tail()}")
                self._buf += chunk

    def mark_cpu(self) -> None:
        """Start of the measured window for this process's CPU time."""
        self._cpu0 = cpu_seconds(self.pid)

    def cpu_since_mark(self) -> float:
        return cpu_seconds(self.pid) - self._cpu0

    def stderr_tail(self) -> str:
        with contextlib.suppress(OSError):
            self._stderr.seek(0)
            tail = self._stderr.read()[-1500:].decode(errors="replace").strip()
            if tail:
                return f"; its stderr ends with:\n{tail}"
        return ""

    def stop(self, grace: float = 2.0) -> None:
        """Close stdin (the child's signal to leave), then terminate, then kill."""
        proc = self.proc
        with contextlib.suppress(OSError):
            if proc.stdin is not None:
                proc.stdin.close()
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.wait(grace)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for stream in (proc.stdout, self._stderr):
            if stream is not None:
                stream.close()


class ProcessGroup:
    """Spawns workers through a link; ``with`` stops every one of them, also on errors."""

    def __init__(self, link: Link, lifetime_s: float = 600.0) -> None:
        self.link = link
        self.lifetime_s = lifetime_s
        self._workers: list[Worker] = []

    def start(self, name: str, side: Side, module: str, role: str, params: Params) -> Worker:
        """Start ``module.ROLES[role](params)`` on ``side``; do not wait for it."""
        argv = [sys.executable, "-c", "from rlbridge.bench.common import worker_main; "
                "worker_main()", module, role, json.dumps(params), str(self.lifetime_s)]
        stderr = tempfile.TemporaryFile()  # noqa: SIM115 - closed by Worker.stop
        proc = self.link.popen(side, argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                               stderr=stderr)
        worker = Worker(name, proc, stderr)
        self._workers.append(worker)
        return worker

    def spawn(self, name: str, side: Side, module: str, role: str, params: Params,
              ready: str = "ready", timeout: float = STARTUP_S) -> tuple[Worker, Params]:
        """:meth:`start`, then wait for the worker's ``ready`` line."""
        worker = self.start(name, side, module, role, params)
        return worker, worker.expect(ready, timeout)

    def diagnostics(self) -> str:
        """The end of every worker's stderr (for the message of a failed run)."""
        return "".join(f"\n--- {w.name} (pid {w.pid}) ---{w.stderr_tail()}" for w in self._workers)

    def close(self) -> None:
        for worker in reversed(self._workers):
            worker.stop()
        self._workers.clear()

    def __enter__(self) -> ProcessGroup:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- child side ----------------------------------------------------------------------------
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
        if n:
            if not self.received:
                self.t_first = now
            self.received += n
            self.t_last = now

    def done(self, now: float) -> bool:
        if self._expected is None:
            msg = self.control.poll("expect")
            if msg is None:
                return False
            self._expected, self._expect_at = int(msg["count"]), now
        if self.received >= self._expected:
            return True
        return now - max(self.t_last, self._expect_at) > self.idle_s

    def report(self, **extra: Any) -> None:
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
    import asyncio
    import logging

    from rlbridge.server import Server, ServerConfig, new_event_loop

    logging.basicConfig(level=params.get("log_level", "INFO"), stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    config = ServerConfig(host=params["host"], port=0, **params.get("config", {}))
    server = Server(config)
    Control(on_eof=server.stop)
    with asyncio.Runner(loop_factory=lambda: new_event_loop(config.use_uvloop)) as runner:
        runner.run(server.serve(install_signal_handlers=True,
                                started=lambda a: emit("ready", port=a.port)))


ROLES: dict[str, Role] = {"server": server_role}


def start_server(group: ProcessGroup, **config: Any) -> tuple[Worker, str, int]:
    """A server on side ``"a"``; returns it, the address clients use, and its port."""
    host = group.link.address("a")
    worker, ready = group.spawn("server", "a", "rlbridge.bench.common", "server",
                                {"host": host, "config": config})
    return worker, host, int(ready["port"])


@dataclass
class Flow:
    """One measured transfer: what the sender and the receiver reported, and CPU per process."""

    sent: Params
    received: Params
    cpu_s: dict[str, float]

    @property
    def rate(self) -> float:
        """Values per second from the sender's first send to the receiver's last arrival."""
        span = float(self.received["t_last"]) - float(self.sent["t_start"])
        n = int(self.received["received"])
        return n / span if n and span > 0 else math.nan

    def cpu_per_million(self, name: str) -> float:
        n = int(self.received["received"])
        return self.cpu_s[name] / n * 1e6 if n else math.nan


def run_flow(sender: Worker, receiver: Worker, measured: Sequence[Worker], timeout: float,
             expect_key: str = "sent") -> Flow:
    """Coordinate one transfer between workers that already said ``ready``.

    Waits until the receiver has joined (it gets the sender's values), starts the sender,
    tells the receiver how many values to expect, and reads every measured process's CPU time
    over the window from ``go`` to the receiver's result.
    """
    receiver.expect("joined", STARTUP_S)
    for w in measured:
        w.mark_cpu()
    sender.send("go")
    sent = sender.expect("sent", timeout)
    receiver.send("expect", count=int(sent[expect_key]))
    received = receiver.expect("result", timeout)
    cpu = {w.name: w.cpu_since_mark() for w in measured}
    return Flow(sent, received, cpu)


def select_cases(cases: Sequence[Any], only: Sequence[str]) -> list[Any]:
    """The rows whose ``key`` is in ``only`` (every row if empty); an unknown key is an error."""
    unknown = set(only) - {c.key for c in cases}
    if unknown:
        raise BenchError(f"unknown row key(s) {', '.join(sorted(unknown))}; the rows are "
                         f"{', '.join(c.key for c in cases)}")
    return [c for c in cases if not only or c.key in only]


# -- statistics ----------------------------------------------------------------------------
def percentile(sorted_values: Sequence[float], q: float) -> float:
    """Linear-interpolated percentile (0..100) of already sorted values; NaN when empty."""
    if not sorted_values:
        return math.nan
    pos = (len(sorted_values) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(sorted_values) - 1)
    return sorted_values[lo] + (sorted_values[hi] - sorted_values[lo]) * (pos - lo)


def median(values: Sequence[float]) -> float:
    """Median ignoring NaN (a skipped repeat); NaN when nothing is left."""
    kept = [v for v in values if not math.isnan(v)]
    return statistics.median(kept) if kept else math.nan


def ratio(value: float, base: float) -> float:
    return value / base if base and not math.isnan(base) and not math.isnan(value) else math.nan


def fmt(value: float, digits: int = 0) -> str:
    """Thousands separators, ``-`` for NaN."""
    return "-" if math.isnan(value) else f"{value:,.{digits}f}"


# -- reports -------------------------------------------------------------------------------
def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def cpu_model() -> str:
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def machine_info() -> dict[str, str]:
    """What a reader needs to judge the figures: cores, CPU, versions, load at the start."""
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return {
        "nproc": str(len(os.sched_getaffinity(0))),
        "cpu": cpu_model(),
        "kernel": platform.release(),
        "python": platform.python_version(),
        "uvloop": _version("uvloop"),
        "msgspec": _version("msgspec"),
        "pyzmq": _version("pyzmq"),
        "eclipse-zenoh": _version("eclipse-zenoh"),
        "load average at start": load,
    }


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    out = ["| " + " | ".join(headers) + " |",
           "|" + "|".join("---:" if i else "---" for i in range(len(headers))) + "|"]
    out += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(out)


def report_header(title: str, command: Sequence[str]) -> str:
    info = machine_info()
    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"### {title}", "", f"Command: `{shlex.join(command)}`  ", f"Date: {when}  "]
    lines += [f"{k}: {v}  " for k, v in info.items()]
    return "\n".join(lines).rstrip() + "\n"


def write_section(path: Path, name: str, body: str) -> None:
    """Replace the ``name`` section of a markdown file (between markers), or append it.

    Each ``rlbridge bench`` command owns one section, so they can share ``docs/benchmarks.md``
    with hand-written text around them.
    """
    begin, end = f"<!-- bench:{name} begin -->", f"<!-- bench:{name} end -->"
    block = f"{begin}\n{body.rstrip()}\n{end}"
    text = path.read_text() if path.exists() else ""
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        text = (text.rstrip() + "\n\n" if text.strip() else "") + block + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def progress(message: str) -> None:
    """One line per run on stderr: the benchmarks take minutes, show that they move."""
    print(f"  {message}", file=sys.stderr, flush=True)
