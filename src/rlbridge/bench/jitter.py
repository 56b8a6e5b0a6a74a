"""``rlbridge bench jitter``: HRT loop jitter per coupling pattern (thesis 5.3) and the GIL study.

How a run is organised, and why:

* The bridge server (``rlbridge serve``) and the publishers run in **separate processes**, so
  their work does not share a GIL with the measured loop; only what the pattern puts in the
  loop's process (the SDK's receive and send threads, the pattern's helpers) does.
* Every measurement is a fresh **worker process** (``python -m rlbridge.bench.jitter worker``)
  that runs one coupling from :mod:`rlbridge.csp.patterns` for ``cycles`` deadlines of a
  ``period`` loop and writes the lateness of every release (``|release - deadline|``, the
  thesis's absolute jitter) to a JSON file. Fresh processes keep patterns from inheriting
  each other's threads, sockets and heap.
* The machine is shared and noisy, so a run has ``repeats`` rounds; each round measures the
  reference loop *and* every pattern (in a rotated order), and figures are medians over the
  rounds. The target is judged against the reference of the same run.
* ``--stress`` runs ``stress --cpu 2 --io 2 --hdd 1`` (the thesis's load, scaled to this box)
  for the whole run, in its own process group, killed at the end.

Suites: ``patterns`` (the thesis figures 5.8-5.10) and ``gil`` (the loop next to the SDK's
threads at 100 Hz and 1 kHz traffic, a pure-Python thread, a ``sendto`` thread, for several
``sys.setswitchinterval`` values, and the loop in its own process with a shared-memory link:
see docs/gil.md).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import math
import os
import platform
import shlex
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from multiprocessing import shared_memory
from pathlib import Path
from typing import Any, Literal

F64 = "std_msgs/msg/Float64"
TOPIC_IN = "/bench/setpoint"
TOPIC_IN_FAST = "/bench/setpoint_fast"
TOPIC_OUT = "/bench/output"

Suite = Literal["patterns", "gil"]


@dataclass(frozen=True)
class Scenario:
    """One measured configuration: a pattern or a GIL-study condition."""

    name: str
    group: str
    label: str
    switch_interval: float | None = None  # None: CPython's default (5 ms)


PATTERN_SCENARIOS: tuple[Scenario, ...] = (
    Scenario("reference", "all", "Reference"),
    Scenario("receive-nonblocking", "receive", "Receive non-blocking (5.3)"),
    Scenario("receive-blocking", "receive", "Receive blocking (5.4)"),
    Scenario("receive-naive", "receive", "Receive naive"),
    Scenario("send-naive", "send", "Send naive"),
    Scenario("send-buffered", "send", "Send buffered (5.5)"),
    Scenario("send-sampled", "send", "Send sampled (5.6)"),
    Scenario("send-loop-100", "send loop", "Send loop 100 Hz (5.10)"),
    Scenario("send-loop-1000", "send loop", "Send loop 1000 Hz (5.10)"),
)

GIL_BASE: tuple[tuple[str, str], ...] = (
    ("reference", "loop alone"),
    ("sdk-100", "SDK threads, 100 Hz in + out"),
    ("sdk-1000", "SDK threads, 1 kHz in + out"),
    ("sendto-1000", "thread calling sendto at 1 kHz"),
    ("pyburn", "thread running pure Python"),
)
GIL_INTERVALS: tuple[float | None, ...] = (None, 0.0005, 0.0001)


def gil_scenarios() -> tuple[Scenario, ...]:
    """Every GIL-study condition at every switch interval, plus the separate-process loop."""
    out = [
        Scenario(name, _interval_label(interval), label, interval)
        for interval in GIL_INTERVALS
        for name, label in GIL_BASE
    ]
    out.append(Scenario("sdk-1000-rtio", "SDK threads real-time",
                        "SDK threads at SCHED_FIFO below the loop, 1 kHz in + out"))
    out.append(Scenario("shm-1000", "separate process",
                        "loop in its own process, shared memory, 1 kHz in + out"))
    return tuple(out)


def _interval_label(interval: float | None) -> str:
    if interval is None:
        return "switch 5 ms (default)"
    return f"switch {interval * 1e6:g} us"


@dataclass(frozen=True)
class JitterConfig:
    """Everything a run needs; built by the CLI."""

    suite: Suite = "patterns"
    cycles: int = 5000
    period: float = 0.001
    repeats: int = 3
    stress: bool = False
    publish_hz: float = 100.0
    only: tuple[str, ...] = ()
    priority: bool = True
    out: Path | None = None
    plot: Path | None = None
    command: str = ""

    @property
    def key(self) -> str:
        """Names this run's generated section, so that variants can share one document."""
        return (f"{self.suite}{'-stress' if self.stress else ''}"
                f"{'' if self.priority else '-nort'}{'-only' if self.only else ''}")

    def markers(self) -> tuple[str, str]:
        """The comments that delimit this run's generated section of the markdown file."""
        return (f"<!-- bench:jitter:{self.key}:begin -->",
                f"<!-- bench:jitter:{self.key}:end -->")

    def scenarios(self) -> tuple[Scenario, ...]:
        chosen = PATTERN_SCENARIOS if self.suite == "patterns" else gil_scenarios()
        if self.only:
            keep = set(self.only)
            chosen = tuple(s for s in chosen if s.name in keep or s.name == "reference")
        return chosen


# -- statistics ---------------------------------------------------------------------------------


def percentile(sorted_values: Sequence[int], percent: float) -> int:
    """Nearest-rank percentile of an already sorted sequence (0 when empty)."""
    if not sorted_values:
        return 0
    rank = max(0, math.ceil(percent / 100 * len(sorted_values)) - 1)
    return int(sorted_values[rank])


@dataclass(frozen=True)
class RunStats:
    """One worker run, reduced."""

    p50_us: float
    p99_us: float
    max_us: float
    samples: int
    missed: int
    round: int = 0

    @classmethod
    def of(cls, lateness_ns: Sequence[int], missed: int, rnd: int = 0) -> RunStats:
        ordered = sorted(lateness_ns)
        return cls(percentile(ordered, 50) / 1e3, percentile(ordered, 99) / 1e3,
                   (ordered[-1] if ordered else 0) / 1e3, len(ordered), missed, rnd)


@dataclass
class ScenarioResult:
    """All repeats of one scenario."""

    scenario: Scenario
    runs: list[RunStats] = field(default_factory=list)
    lateness: list[list[int]] = field(default_factory=list)
    info: list[dict[str, Any]] = field(default_factory=list)

    def median(self, attr: str) -> float:
        values = [float(getattr(r, attr)) for r in self.runs]
        return statistics.median(values) if values else math.nan

    def paired_delta(self, ref: ScenarioResult, attr: str = "p99_us") -> float:
        """Median over rounds of (this - the reference measured in the same round).

        Pairing cancels the load that drifts from round to round on a shared machine.
        """
        theirs = {r.round: float(getattr(r, attr)) for r in ref.runs}
        deltas = [float(getattr(r, attr)) - theirs[r.round] for r in self.runs
                  if r.round in theirs]
        return statistics.median(deltas) if deltas else math.nan


# -- the processes around a run -----------------------------------------------------------------


def _free_port() -> int:
    """A port free for both TCP and UDP right now (the server binds both)."""
    for _ in range(50):
        with socket.socket() as tcp, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            tcp.bind(("127.0.0.1", 0))
            port = int(tcp.getsockname()[1])
            try:
                udp.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError("no free port for the bridge server")


class Children:
    """Every process a run spawns; each in its own group, all killed in :meth:`close`."""

    def __init__(self) -> None:
        self._procs: list[subprocess.Popen[bytes]] = []

    def spawn(self, argv: Sequence[str], *, cwd: str | None = None,
              log: Path | None = None) -> subprocess.Popen[bytes]:
        out = open(log, "wb") if log is not None else subprocess.DEVNULL  # noqa: SIM115
        try:
            proc = subprocess.Popen(argv, cwd=cwd, stdin=subprocess.DEVNULL, stdout=out,
                                    stderr=subprocess.STDOUT, start_new_session=True)
        finally:
            if log is not None:
                out.close()  # type: ignore[union-attr]
        self._procs.append(proc)
        return proc

    def close(self) -> None:
        """SIGTERM each group, wait briefly, then SIGKILL what is left."""
        for proc in self._procs:
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + 5.0
        for proc in self._procs:
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(5.0)
        self._procs.clear()


def _python(*args: str) -> list[str]:
    return [sys.executable, "-m", "rlbridge.bench.jitter", *args]


def _wait_for_server(port: int, timeout: float = 15.0) -> None:
    from rlbridge.csp.bridge import Bridge
    from rlbridge.csp.connection import ConnectionFailed

    deadline = time.monotonic() + timeout
    while True:
        try:
            Bridge.connect("127.0.0.1", port, timeout=1.0, name="bench-probe").close()
            return
        except ConnectionFailed:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


@contextlib.contextmanager
def environment(config: JitterConfig, workdir: Path, seconds: float) -> Iterator[int]:
    """Server, publishers and (optionally) stress for ``seconds``; yields the server port."""
    children = Children()
    try:
        port = _free_port()
        children.spawn([sys.executable, "-c", "from rlbridge.cli import main; main()",
                        "serve", "--port", str(port), "--nodelay", "--timeout-ms", "5000"],
                       log=workdir / "server.log")
        _wait_for_server(port)
        rates = [(TOPIC_IN, config.publish_hz)]
        if config.suite == "gil":
            rates.append((TOPIC_IN_FAST, 1000.0))
        for topic, rate in rates:
            children.spawn(_python("publisher", "--port", str(port), "--topic", topic,
                                   "--rate", str(rate), "--seconds", str(seconds)),
                           log=workdir / f"publisher{topic.replace('/', '_')}.log")
        if config.stress:
            stress = shutil.which("stress")
            if stress is None:
                raise RuntimeError("--stress needs the 'stress' program: apt-get install stress")
            children.spawn([stress, "--cpu", "2", "--io", "2", "--hdd", "1", "--hdd-bytes",
                            "64M", "--timeout", f"{math.ceil(seconds)}s"],
                           cwd=str(workdir), log=workdir / "stress.log")
        time.sleep(0.5)  # publishers connected and flowing
        yield port
    finally:
        children.close()


def run_worker(scenario: Scenario, config: JitterConfig, port: int,
               workdir: Path, tag: str) -> dict[str, Any]:
    """Run one scenario in a fresh process; return its JSON result."""
    result = workdir / f"{tag}.json"
    argv = _python("worker", "--scenario", scenario.name, "--port", str(port),
                   "--cycles", str(config.cycles), "--period", repr(config.period),
                   "--result", str(result))
    interval = scenario.switch_interval
    if interval is None and config.suite == "gil":
        interval = 0.005  # CPython's default, kept even though Bridge.connect shortens it
    if interval is not None:
        argv += ["--switch-interval", repr(interval)]
    if not config.priority:
        argv.append("--no-priority")
    children = Children()
    try:
        proc = children.spawn(argv, log=workdir / f"{tag}.log")
        proc.wait(config.cycles * config.period * 3 + 60)
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"worker {tag} did not finish; see {workdir / (tag + '.log')}"
                           ) from None
    finally:
        children.close()
    if proc.returncode != 0 or not result.exists():
        log = (workdir / f"{tag}.log").read_text(errors="replace")[-2000:]
        raise RuntimeError(f"worker {tag} failed (exit {proc.returncode}):\n{log}")
    data: dict[str, Any] = json.loads(result.read_text())
    return data


def run_suite(config: JitterConfig, progress: Callable[[str], None] = print
              ) -> list[ScenarioResult]:
    """Measure every scenario ``repeats`` times (rotated order per round)."""
    scenarios = config.scenarios()
    results = [ScenarioResult(s) for s in scenarios]
    per_run = config.cycles * config.period + 3.0
    seconds = per_run * len(scenarios) * config.repeats * 1.5 + 60
    with tempfile.TemporaryDirectory(prefix="rlbridge-jitter-") as tmp:
        workdir = Path(tmp)
        with environment(config, workdir, seconds) as port:
            for rnd in range(config.repeats):
                order = list(range(len(scenarios)))
                shift = rnd % len(order)
                order = order[shift:] + order[:shift]
                for index in order:
                    sc = scenarios[index]
                    tag = f"r{rnd}-{sc.name}-{sc.switch_interval or 'default'}"
                    try:
                        data = run_worker(sc, config, port, workdir, tag)
                    except RuntimeError as exc:  # one bad run must not lose the others
                        progress(f"round {rnd + 1}/{config.repeats} {sc.name}: {exc}")
                        continue
                    stats = RunStats.of(data["lateness_ns"], data["missed"], rnd)
                    results[index].runs.append(stats)
                    results[index].lateness.append(data["lateness_ns"])
                    results[index].info.append(data["info"])
                    progress(f"round {rnd + 1}/{config.repeats} {sc.group:>24} "
                             f"{sc.name:<20} p50 {stats.p50_us:8.1f} us  p99 "
                             f"{stats.p99_us:8.1f} us  max {stats.max_us:8.1f} us  "
                             f"missed {stats.missed}")
    return results


# -- the worker: one scenario in this process ----------------------------------------------------


def _receive_law() -> Callable[[Any], None]:
    state = [0.0]

    def law(value: Any) -> None:
        state[0] += 0.1 * (float(value) - state[0])  # a first-order filter: a tiny controller

    return law


def _send_law() -> Callable[[], float]:
    k = [0]

    def law() -> float:
        k[0] += 1
        return math.sin(k[0] * 0.001)

    return law


def _wait_first_value(channel: Any, timeout: float = 5.0) -> bool:
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


def _probed(fn: Callable[..., Any], info: dict[str, Any]) -> Callable[..., Any]:
    """Wrap a control law so that its first call records the HRT thread's scheduling."""

    def probe(*args: Any) -> Any:
        if "policy" not in info:
            info["policy"] = _policy()
        return fn(*args)

    return probe


def worker_main(args: argparse.Namespace) -> None:  # noqa: PLR0915  one dispatch on scenario
    """Run one scenario in this process and write its lateness samples as JSON."""
    from rlbridge.csp import patterns
    from rlbridge.csp.bridge import DEFAULT_SWITCH_INTERVAL, Bridge

    if args.switch_interval is not None:
        sys.setswitchinterval(args.switch_interval)
    name: str = args.scenario
    kwargs: dict[str, Any] = {"period": args.period, "cycles": args.cycles,
                              "priority": args.priority}
    info: dict[str, Any] = {"switch_interval": sys.getswitchinterval()}
    stop = threading.Event()
    extra: list[threading.Thread] = []
    bridge: Bridge | None = None
    coupling: patterns.Coupling
    if name == "shm-1000":
        result = shm_parent(args)
        Path(args.result).write_text(json.dumps(result))
        return
    try:
        rate = {"send-loop-100": 100.0, "send-loop-1000": 1000.0, "sdk-100": 100.0,
                "sdk-1000": 1000.0, "sdk-1000-rtio": 1000.0}.get(name)
        if name not in ("reference", "pyburn", "sendto-1000"):
            # an explicit --switch-interval wins over Bridge.connect's default
            keep = None if args.switch_interval is not None else DEFAULT_SWITCH_INTERVAL
            bridge = Bridge.connect("127.0.0.1", args.port, nodelay=True, send_rate_hz=rate,
                                    name=f"bench-{name}", switch_interval=keep)
        if name == "sdk-1000-rtio" and bridge is not None:
            info["io_threads"] = "SCHED_FIFO 40" if bridge.set_io_priority(40) else "refused"
        recv, send = _probed(_receive_law(), info), _probed(_send_law(), info)
        if bridge is None:
            coupling = patterns.reference(lambda: recv(send()), **kwargs)
        elif name == "receive-nonblocking":
            coupling = patterns.receive_nonblocking(bridge, TOPIC_IN, F64, recv, **kwargs)
        elif name == "receive-blocking":
            coupling = patterns.receive_blocking(bridge, TOPIC_IN, F64, recv, **kwargs)
        elif name == "receive-naive":
            coupling = patterns.receive_naive(bridge, TOPIC_IN, F64, recv, **kwargs)
        elif name == "send-naive":
            coupling = patterns.send_naive(bridge, TOPIC_OUT, F64, send, **kwargs)
        elif name == "send-buffered":
            coupling = patterns.send_buffered(bridge, TOPIC_OUT, F64, send, **kwargs)
        elif name == "send-sampled":
            coupling = patterns.send_sampled(bridge, TOPIC_OUT, F64, send, **kwargs)
        elif name.startswith("send-loop-"):
            coupling = patterns.send_loop(bridge, TOPIC_OUT, F64, send, **kwargs)
        elif name.startswith("sdk-"):
            coupling = _sdk_coupling(bridge, TOPIC_IN if name == "sdk-100" else TOPIC_IN_FAST,
                                     recv, send, kwargs)
        else:
            raise SystemExit(f"unknown scenario {name!r}")
        if name == "pyburn":
            extra.append(threading.Thread(target=_pyburn, args=(stop,), name="pyburn"))
        elif name == "sendto-1000":
            extra.append(threading.Thread(target=_sendto, args=(stop, 1000.0), name="sendto"))
        incoming = coupling.channels.get("in")
        if incoming is not None and not _wait_first_value(incoming):
            raise SystemExit(f"no value arrived on {TOPIC_IN} within 5 s: is the publisher up?")
        extra.append(threading.Thread(
            target=_watchdog, args=(coupling, stop, args.cycles * args.period + 15.0, info),
            name="watchdog"))
        for thread in extra:
            thread.start()
        clocks = _thread_clocks()
        wall = time.monotonic()
        coupling.run()
        wall = time.monotonic() - wall
        info["thread_cpu_percent"] = {name: round(100 * (time.clock_gettime(clock) - t0) / wall, 2)
                                      for name, (clock, t0) in clocks.items()}
        info.update(_channel_info(coupling))
        loop = coupling.loop
        stats = loop.stats()
        result = {"scenario": name, "lateness_ns": loop.lateness_ns(), "missed": stats.missed,
                  "released": loop.released, "info": info}
    finally:
        stop.set()
        for thread in extra:
            thread.join(5.0)
        if bridge is not None:
            bridge.close()
    Path(args.result).write_text(json.dumps(result))


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


def _sdk_coupling(bridge: Any, topic: str, recv: Callable[[Any], None],
                  send: Callable[[], float], kwargs: dict[str, Any]) -> Any:
    """GIL study: the loop reads a non-blocking input and writes a send-loop output."""
    from rlbridge.csp import patterns

    incoming = bridge.subscribe(topic, F64, blocking=False, buffer_size=1, initial=0.0)
    out = bridge.publish(TOPIC_OUT, F64, through_buffer=True)

    def body() -> None:
        recv(incoming.read())
        out.write(send())

    return patterns.Coupling("sdk", body, channels={"in": incoming, "out": out},
                             closers=[incoming.close], **kwargs)


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


# -- the separate-process prototype (docs/gil.md) ---------------------------------------------


class ShmLink:
    """Prototype: a latest-value slot in and an SPSC ring out, in shared memory.

    Layout (int64/float64 words): 0 set-point sequence (seqlock: odd while writing),
    1 set-point value, 2 ring head (written by the HRT process), 3 ring tail (written by the
    SDK process), 8.. ring slots. Relies on aligned 8-byte stores being atomic and stores
    being seen in program order (x86-64 TSO); a prototype, not a portable implementation.
    """

    HEADER = 8

    def __init__(self, shm: shared_memory.SharedMemory, capacity: int) -> None:
        self.shm = shm
        self.capacity = capacity
        buf = shm.buf
        assert buf is not None
        self._q = buf.cast("q")
        self._d = buf.cast("d")

    @classmethod
    def create(cls, capacity: int = 4096) -> ShmLink:
        shm = shared_memory.SharedMemory(create=True, size=8 * (cls.HEADER + capacity))
        return cls(shm, capacity)

    @classmethod
    def attach(cls, name: str, capacity: int = 4096) -> ShmLink:
        shm = shared_memory.SharedMemory(name=name)
        # Python < 3.13 registers an attached segment with the resource tracker, which
        # would unlink it when this process exits; the creator owns it (track=False is 3.13+).
        from multiprocessing import resource_tracker

        resource_tracker.unregister(shm._name, "shared_memory")  # type: ignore[attr-defined]
        return cls(shm, capacity)

    def put_setpoint(self, value: float) -> None:
        q = self._q
        seq = q[0]
        q[0] = seq + 1
        self._d[1] = value
        q[0] = seq + 2

    def get_setpoint(self, fallback: float) -> float:
        q = self._q
        for _ in range(4):
            before = q[0]
            value = self._d[1]
            if before % 2 == 0 and q[0] == before:
                return float(value)
        return fallback

    def push(self, value: float) -> bool:
        q = self._q
        head = q[2]
        if head - q[3] >= self.capacity:
            return False
        self._d[self.HEADER + head % self.capacity] = value
        q[2] = head + 1
        return True

    def drain(self) -> list[float]:
        q = self._q
        head, tail = q[2], q[3]
        d = self._d
        cap = self.capacity
        values = [float(d[self.HEADER + i % cap]) for i in range(tail, head)]
        q[3] = head
        return values

    def close(self) -> None:
        self._q.release()
        self._d.release()
        self.shm.close()


def shm_parent(args: argparse.Namespace) -> dict[str, Any]:
    """SDK process of the prototype: Bridge at 1 kHz both ways, a pump, the HRT child."""
    from rlbridge.csp.bridge import Bridge
    from rlbridge.csp.timer import PeriodicTimer

    link = ShmLink.create()
    children = Children()
    stop = threading.Event()
    child_result = Path(args.result + ".child")
    try:
        if args.switch_interval is not None:
            sys.setswitchinterval(args.switch_interval)
        with Bridge.connect("127.0.0.1", args.port, nodelay=True, send_rate_hz=1000.0,
                            name="bench-shm-sdk", switch_interval=None) as bridge:
            incoming = bridge.subscribe(TOPIC_IN_FAST, F64, blocking=False, initial=0.0)
            out = bridge.publish(TOPIC_OUT, F64, through_buffer=True)
            _wait_first_value(incoming)

            def pump() -> None:
                timer = PeriodicTimer(0.001, history=1)
                while timer.wait_next(stop):
                    link.put_setpoint(float(incoming.read()))
                    values = link.drain()
                    if values:
                        out.write_many(values)

            pumper = threading.Thread(target=pump, name="shm-pump")
            pumper.start()
            try:
                argv = _python("shm-loop", "--name", link.shm.name, "--cycles",
                               str(args.cycles), "--period", repr(args.period),
                               "--result", str(child_result))
                if not args.priority:
                    argv.append("--no-priority")
                proc = children.spawn(argv, log=Path(args.result + ".child.log"))
                proc.wait(args.cycles * args.period * 3 + 60)
            finally:
                stop.set()
                pumper.join(5.0)
            stats = out.statistics()
        data: dict[str, Any] = json.loads(child_result.read_text())
        data["info"]["sdk_values_sent"] = stats.written
        return data
    finally:
        children.close()
        link.close()
        link.shm.unlink()


def shm_loop_main(args: argparse.Namespace) -> None:
    """HRT process of the prototype: one thread, no SDK; talks to shared memory only."""
    from rlbridge.csp import patterns

    link = ShmLink.attach(args.name)
    info: dict[str, Any] = {"switch_interval": sys.getswitchinterval()}
    recv, send = _receive_law(), _send_law()
    latest = [0.0]
    dropped = [0]

    def body() -> None:
        latest[0] = link.get_setpoint(latest[0])
        recv(latest[0])
        if not link.push(send()):
            dropped[0] += 1

    try:
        coupling = patterns.Coupling("shm", _probed(body, info), period=args.period,
                                     cycles=args.cycles, priority=args.priority)
        coupling.run()
        loop = coupling.loop
        info["ring_dropped"] = dropped[0]
        result = {"scenario": "shm-1000", "lateness_ns": loop.lateness_ns(),
                  "missed": loop.stats().missed, "released": loop.released, "info": info}
    finally:
        link.close()
    Path(args.result).write_text(json.dumps(result))


def publisher_main(args: argparse.Namespace) -> None:
    """Publish a sine on ``--topic`` at ``--rate`` for ``--seconds`` (a separate process)."""
    from rlbridge.csp.bridge import Bridge
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


# -- report ------------------------------------------------------------------------------------


def machine_info() -> dict[str, str]:
    """What the figures were measured on."""
    cpu = "unknown"
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    load = "unknown"
    with contextlib.suppress(OSError):
        load = " ".join(Path("/proc/loadavg").read_text().split()[:3])
    return {
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "host": f"{platform.system()} {platform.release()} {platform.machine()}",
        "cpu": f"{cpu}, {os.cpu_count()} CPUs",
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "load": load,
    }


def target_ok(ref_p99: float, delta_p99: float) -> bool:
    """The target: p99 within 10 % or 20 us (whichever is larger) of the reference's."""
    return delta_p99 <= max(0.1 * ref_p99, 20.0)


def render_markdown(config: JitterConfig, results: list[ScenarioResult],
                    machine: dict[str, str], plot: Path | None) -> str:
    """The generated section of docs/jitter.md or docs/gil.md."""
    begin, end = config.markers()
    lines = [
        begin,
        f"Command: `{config.command or 'rlbridge bench jitter'}`",
        "",
        f"Measured {machine['date']} on {machine['host']}, {machine['cpu']}, "
        f"{machine['python']}; load average before the run {machine['load']}. "
        f"{config.cycles} deadlines of a {config.period * 1e6:g} us loop per run, "
        f"{config.repeats} rounds, stress {'on' if config.stress else 'off'}, HRT thread "
        f"{_policies(results)}.",
        "",
        "Figures are medians over the rounds of each run's p50 / p99 / max of the absolute "
        "jitter |release - deadline| in microseconds. *d p99* is the median over the rounds "
        "of (p99 - p99 of the reference measured in the same round), which cancels the load "
        "that drifts between rounds; the target is d p99 <= max(10 % of the reference's "
        "p99, 20 us). *missed*: releases skipped because the loop was still busy (median per "
        "run); *samples*: releases recorded (median per run).",
        "",
        "| group | scenario | p50 us | p99 us | max us | samples | missed | d p99 us | target |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    refs = {r.scenario.group: r for r in results if r.scenario.name == "reference"}
    default_ref = next((r for r in results if r.scenario.name == "reference"), None)
    for res in results:
        ref = refs.get(res.scenario.group, default_ref)
        delta, verdict = "", ""
        if ref is not None and res is not ref:
            paired = res.paired_delta(ref)
            ok = target_ok(ref.median("p99_us"), paired)
            delta, verdict = f"{paired:+.0f}", "met" if ok else "missed"
            if "naive" in res.scenario.name:
                # p99 of a naive receive is capped at one period (late releases are
                # skipped, see "missed"): the target is for the proper patterns only
                verdict = "n/a (naive)"
        lines.append(
            f"| {res.scenario.group} | {res.scenario.label} | {res.median('p50_us'):.0f} | "
            f"{res.median('p99_us'):.0f} | {res.median('max_us'):.0f} | "
            f"{res.median('samples'):.0f} | {res.median('missed'):.0f} | {delta} | "
            f"{verdict} |")
    lines += ["", "Per round (p99 us):", "",
              "| scenario | " + " | ".join(f"round {i + 1}" for i in range(config.repeats))
              + " |", "|---|" + "---:|" * config.repeats]
    for res in results:
        by_round = {r.round: f"{r.p99_us:.0f}" for r in res.runs}
        cells = " | ".join(by_round.get(i, "failed") for i in range(config.repeats))
        lines.append(f"| {res.scenario.group}: {res.scenario.name} | {cells} |")
    if plot is not None:
        lines += ["", f"![absolute jitter per cycle]({plot.name})"]
    lines.append(end)
    return "\n".join(lines) + "\n"


def _policies(results: list[ScenarioResult]) -> str:
    seen = sorted({str(i.get("policy", "unknown")) for r in results for i in r.info})
    return " / ".join(seen) if seen else "unknown"


def write_section(path: Path, section: str, title: str, markers: tuple[str, str]) -> None:
    """Replace the generated section of ``path``, keeping the prose around it."""
    begin, end = markers
    if path.exists():
        text = path.read_text()
        if begin in text and end in text:
            head, rest = text.split(begin, 1)
            tail = rest.split(end, 1)[1]
            path.write_text(head + section.rstrip("\n") + tail)
            return
        path.write_text(text.rstrip("\n") + "\n\n" + section)
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"# {title}\n\n{section}")


def _median_round(res: ScenarioResult) -> int:
    order = sorted(range(len(res.runs)), key=lambda i: res.runs[i].p99_us)
    return order[len(order) // 2] if order else 0


def plot_results(config: JitterConfig, results: list[ScenarioResult], path: Path) -> None:
    """Absolute jitter per cycle, one panel per group (thesis figures 5.8-5.10 style)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref = next((r for r in results if r.scenario.name == "reference"), None)
    groups: list[str] = []
    for res in results:
        if res.scenario.name != "reference" and res.scenario.group not in groups:
            groups.append(res.scenario.group)
    if config.suite == "gil":
        _plot_gil(plt, results, path)
        return
    fig, axes = plt.subplots(len(groups), 1, figsize=(10, 3.2 * len(groups)), squeeze=False)
    rnd = _median_round(ref) if ref is not None else 0
    for ax, group in zip(axes[:, 0], groups, strict=True):
        members = ([ref] if ref is not None else []) + [
            r for r in results if r.scenario.group == group and r.scenario.name != "reference"]
        for res in members:
            samples = res.lateness[min(rnd, len(res.lateness) - 1)]
            stats = res.runs[min(rnd, len(res.runs) - 1)]
            ax.plot(range(len(samples)), [max(s / 1e3, 0.1) for s in samples],
                    ".", markersize=1.5,
                    label=f"{res.scenario.label} (p99 {stats.p99_us:.0f} us, "
                          f"max {stats.max_us:.0f} us)")
        ax.set_yscale("log")
        ax.set_ylabel("absolute jitter [us]")
        ax.set_title(f"{group}: {config.period * 1e6:g} us loop"
                     f"{', stressed' if config.stress else ''} (round {rnd + 1})")
        ax.legend(loc="upper right", fontsize=7, markerscale=6)
        ax.grid(True, which="both", alpha=0.3)
    axes[-1, 0].set_xlabel("release number (a naive receive releases once per message)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_gil(plt: Any, results: list[ScenarioResult], path: Path) -> None:
    present = {r.scenario.name for r in results}
    names = [name for name, _ in GIL_BASE if name in present]
    fig, ax = plt.subplots(figsize=(10, 4.5))
    width = 0.8 / (len(GIL_INTERVALS) + 1)
    for k, interval in enumerate(GIL_INTERVALS):
        label = _interval_label(interval)
        p99 = []
        p50 = []
        for name in names:
            res = next((r for r in results if r.scenario.name == name
                        and r.scenario.switch_interval == interval), None)
            p99.append(res.median("p99_us") if res else math.nan)
            p50.append(res.median("p50_us") if res else math.nan)
        xs = [i + k * width for i in range(len(names))]
        ax.bar(xs, p99, width, label=f"p99, {label}", alpha=0.85)
        ax.scatter(xs, p50, marker="_", color="black", s=80, zorder=3)
    extras = [r for r in results if r.scenario.name in ("sdk-1000-rtio", "shm-1000")]
    ticks = [i + width for i in range(len(names))]
    for j, res in enumerate(extras):
        x = len(names) + j
        ax.bar([x], [res.median("p99_us")], width * 2, color=("tab:purple", "tab:red")[j % 2],
               label=f"p99, {res.scenario.label} (switch 5 ms)")
        ax.scatter([x], [res.median("p50_us")], marker="_", color="black", s=80, zorder=3)
        ticks.append(x)
    ax.set_xticks(ticks, names + [r.scenario.name for r in extras], fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("absolute jitter [us] (bar p99, tick p50)")
    ax.set_title("1 kHz loop next to other threads in one interpreter")
    ax.legend(fontsize=7)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


@contextlib.contextmanager
def _exit_on_signals() -> Iterator[None]:
    """SIGTERM/SIGINT raise SystemExit, so the ``finally`` blocks kill every child process.

    (A backgrounded shell job starts with SIGINT ignored and Python's default SIGTERM
    action skips ``finally``.) The previous handlers are restored on the way out.
    """

    def leave(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, leave) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def run(config: JitterConfig, progress: Callable[[str], None] = print
        ) -> list[ScenarioResult]:
    """Measure, then write the plot and the markdown section when asked to."""
    machine = machine_info()
    with _exit_on_signals():
        results = run_suite(config, progress)
    if config.plot is not None:
        plot_results(config, results, config.plot)
    section = render_markdown(config, results, machine, config.plot)
    if config.out is not None:
        title = "HRT loop jitter per coupling pattern" if config.suite == "patterns" \
            else "The GIL and the HRT loop"
        write_section(config.out, section, title, config.markers())
        raw = config.out.with_name(f"{config.out.stem}.{config.key}.json")
        raw.write_text(json.dumps({
            "config": {k: str(v) for k, v in asdict(config).items()},
            "machine": machine,
            "results": [{"scenario": asdict(r.scenario), "runs": [asdict(s) for s in r.runs],
                         "info": r.info} for r in results],
        }, indent=1))
    progress(section)
    return results


def pooled_deltas(paths: Sequence[Path]) -> str:
    """Pool the per-round differences to the same-round reference over several runs' JSON.

    One run's five rounds cannot separate a 200 us effect from a machine whose reference p99
    swings by milliseconds between rounds; the same condition measured in several runs can.
    Returns a markdown table: median difference of p50 and p99, and in how many rounds the
    p99 was worse than the reference's.
    """
    pool: dict[tuple[str, str], tuple[list[float], list[float]]] = {}
    for path in paths:
        data = json.loads(path.read_text())
        results = data["results"]
        refs = {r["scenario"]["switch_interval"]: r for r in results
                if r["scenario"]["name"] == "reference"}
        for res in results:
            sc = res["scenario"]
            if sc["name"] == "reference":
                continue
            ref = refs.get(sc["switch_interval"], refs.get(None))
            if ref is None:
                continue
            by_round = {run["round"]: run for run in ref["runs"]}
            d50, d99 = pool.setdefault((sc["name"], sc["group"]), ([], []))
            for run in res["runs"]:
                other = by_round.get(run["round"])
                if other is not None:
                    d50.append(run["p50_us"] - other["p50_us"])
                    d99.append(run["p99_us"] - other["p99_us"])
    lines = ["| scenario | group | rounds | d p50 us | d p99 us | p99 worse than ref |",
             "|---|---|---:|---:|---:|---:|"]
    for (name, group), (d50, d99) in pool.items():
        worse = sum(1 for d in d99 if d > 0)
        lines.append(f"| {name} | {group} | {len(d99)} | {statistics.median(d50):+.0f} | "
                     f"{statistics.median(d99):+.0f} | {worse}/{len(d99)} |")
    return "\n".join(lines)


# -- python -m rlbridge.bench.jitter {worker,publisher,shm-loop,pool} --------------------------


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m rlbridge.bench.jitter")
    sub = parser.add_subparsers(dest="role", required=True)
    worker = sub.add_parser("worker", help="run one scenario (spawned by the benchmark)")
    worker.add_argument("--scenario", required=True)
    worker.add_argument("--port", type=int, required=True)
    worker.add_argument("--cycles", type=int, default=5000)
    worker.add_argument("--period", type=float, default=0.001)
    worker.add_argument("--switch-interval", type=float, default=None)
    worker.add_argument("--no-priority", dest="priority", action="store_false")
    worker.add_argument("--result", required=True)
    pub = sub.add_parser("publisher", help="publish a sine at a rate, for a bounded time")
    pub.add_argument("--host", default="127.0.0.1")
    pub.add_argument("--port", type=int, required=True)
    pub.add_argument("--topic", default=TOPIC_IN)
    pub.add_argument("--rate", type=float, default=100.0)
    pub.add_argument("--seconds", type=float, default=60.0)
    shm = sub.add_parser("shm-loop", help="the HRT process of the shared-memory prototype")
    shm.add_argument("--name", required=True)
    shm.add_argument("--cycles", type=int, default=5000)
    shm.add_argument("--period", type=float, default=0.001)
    shm.add_argument("--no-priority", dest="priority", action="store_false")
    shm.add_argument("--result", required=True)
    pool = sub.add_parser("pool", help="pool same-round differences over several runs' JSON")
    pool.add_argument("json", nargs="+", type=Path)
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of the helper processes."""
    args = _parser().parse_args(argv)
    if args.role == "worker":
        worker_main(args)
    elif args.role == "publisher":
        publisher_main(args)
    elif args.role == "pool":
        print(pooled_deltas(args.json))
    else:
        shm_loop_main(args)


def command_line(argv: Sequence[str]) -> str:
    """The command as typed, for the report."""
    return "rlbridge " + shlex.join(argv)


if __name__ == "__main__":
    main()
