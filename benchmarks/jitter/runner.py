"""The processes around a ``python -m benchmarks.jitter run`` run, and the run itself.

* The bridge server (``rlbridge serve``) and the publishers run in **separate processes** for
  the whole run, so their work does not share a GIL with the measured loop and the reference
  loop sees the same background load as the patterns.
* Every measurement is a fresh **worker process** (``python -m benchmarks.jitter worker``,
  :mod:`benchmarks.jitter.worker`), so patterns do not inherit each other's threads,
  sockets and heap. Every worker, the reference's included, gets the same treatment: the
  same priority (``PriParallel``), the same CPU for the loop thread (``--cpu``), the same
  memory locking and timer slack.
* ``repeats`` rounds, each measuring every scenario in a rotated order with the reference
  between every two of them (:meth:`~benchmarks.jitter.config.JitterConfig.round_order`);
  figures are compared with the reference runs next to them.
* ``--stress`` runs ``stress --cpu 2 --io 2 --hdd 1`` (the thesis's load, scaled to this box)
  for the whole run, in its own process group, killed at the end.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from benchmarks import module_argv
from benchmarks.jitter.config import (
    TOPIC_IN,
    TOPIC_IN_FAST,
    JitterConfig,
    RunStats,
    Scenario,
    ScenarioResult,
)


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


def python_module(*args: str) -> list[str]:
    """argv of a helper process of this benchmark (``python -m benchmarks.jitter ...``)."""
    return module_argv("benchmarks.jitter", *args)


def _wait_for_server(port: int, timeout: float = 15.0) -> None:
    from rlbridge.client.bridge import Bridge
    from rlbridge.client.session.connection import ConnectionFailed

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
    """Server, publishers and (optionally) stress for ``seconds``; yields the server port.

    Stress loads every CPU; then, with ``isolate``, this process and all it starts from here on
    (server, publishers, workers and their threads) keep off the loops' CPU, and only each
    worker's loop thread is pinned onto it. On a kernel without full preemption (this VM:
    ``PREEMPT_NONE``) a thread inside a system call cannot be preempted, so the I/O of the
    bridge on the loop's CPU would delay the loop whatever its priority.
    """
    children = Children()
    try:
        if config.stress:
            stress = shutil.which("stress")
            if stress is None:
                raise RuntimeError("--stress needs the 'stress' program: apt-get install stress")
            children.spawn([stress, "--cpu", "2", "--io", "2", "--hdd", "1", "--hdd-bytes",
                            "64M", "--timeout", f"{math.ceil(seconds)}s"],
                           cwd=str(workdir), log=workdir / "stress.log")
        with kept_off(config.cpu if config.isolate else None):
            port = _free_port()
            children.spawn([sys.executable, "-c", "from rlbridge.cli import main; main()",
                            "serve", "--port", str(port), "--nodelay", "--timeout-ms", "5000"],
                           log=workdir / "server.log")
            _wait_for_server(port)
            rates = [(TOPIC_IN, config.publish_hz)]
            if config.suite == "gil":
                rates.append((TOPIC_IN_FAST, 1000.0))
            for topic, rate in rates:
                children.spawn(python_module("publisher", "--port", str(port), "--topic",
                                             topic, "--rate", str(rate), "--seconds",
                                             str(seconds)),
                               log=workdir / f"publisher{topic.replace('/', '_')}.log")
            time.sleep(0.5)  # publishers connected and flowing
            yield port
    finally:
        children.close()


@contextlib.contextmanager
def kept_off(cpu: int | None) -> Iterator[None]:
    """This process (and what it starts meanwhile) runs on every CPU but ``cpu``."""
    if cpu is None or not hasattr(os, "sched_setaffinity"):
        yield
        return
    before = os.sched_getaffinity(0)
    others = before - {cpu}
    if not others:
        yield  # a single CPU: nothing to keep off
        return
    os.sched_setaffinity(0, others)
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def run_worker(scenario: Scenario, config: JitterConfig, port: int,
               workdir: Path, tag: str) -> dict[str, Any]:
    """Run one scenario in a fresh process; return its JSON result."""
    result = workdir / f"{tag}.json"
    argv = python_module("worker", "--scenario", scenario.name, "--port", str(port),
                   "--cycles", str(config.cycles), "--period", repr(config.period),
                   "--result", str(result))
    interval = scenario.switch_interval
    if interval is None and config.suite == "gil":
        interval = 0.005  # CPython's default, explicit: the loop would hold a shorter one
    if interval is not None:
        argv += ["--switch-interval", repr(interval)]
    argv += treatment_args(config.priority, config.cpu, config.mlock)
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
    """Measure every scenario ``repeats`` times, in :meth:`JitterConfig.round_order`."""
    scenarios = config.scenarios()
    results = [ScenarioResult(s) for s in scenarios]
    per_run = config.cycles * config.period + 3.0
    seconds = per_run * len(config.round_order(0)) * config.repeats * 1.5 + 60
    with tempfile.TemporaryDirectory(prefix="rlbridge-jitter-") as tmp:
        workdir = Path(tmp)
        with environment(config, workdir, seconds) as port:
            for rnd in range(config.repeats):
                for seq, index in enumerate(config.round_order(rnd)):
                    sc = scenarios[index]
                    tag = f"r{rnd}-{seq}-{sc.name}-{sc.switch_interval or 'default'}"
                    try:
                        data = run_worker(sc, config, port, workdir, tag)
                    except RuntimeError as exc:  # one bad run must not lose the others
                        progress(f"round {rnd + 1}/{config.repeats} {sc.name}: {exc}")
                        continue
                    stats = RunStats.of(data["lateness_ns"], data["missed"], rnd, seq,
                                        data["info"].get("steal_ms"))
                    results[index].runs.append(stats)
                    results[index].lateness.append(data["lateness_ns"])
                    results[index].info.append(data["info"])
                    steal = "" if stats.steal_ms is None else f"  steal {stats.steal_ms:.0f} ms"
                    progress(f"round {rnd + 1}/{config.repeats} {sc.group:>24} "
                             f"{sc.name:<20} p50 {stats.p50_us:8.1f} us  p99 "
                             f"{stats.p99_us:8.1f} us  max {stats.max_us:8.1f} us  "
                             f"missed {stats.missed}{steal}")
    return results


def treatment_args(priority: bool, cpu: int | None, mlock: bool) -> list[str]:
    """The worker options that make every loop process's conditions the same."""
    argv = [] if priority else ["--no-priority"]
    if cpu is not None:
        argv += ["--cpu", str(cpu)]
    return argv if mlock else [*argv, "--no-mlock"]


@contextlib.contextmanager
def exit_on_signals() -> Iterator[None]:
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

