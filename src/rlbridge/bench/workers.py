"""The parent side of a benchmark: where its processes run, and how it drives them.

Every measured party runs in its own process, as it would in deployment: a publisher, a
server, a subscriber (or a baseline's sender and receiver). The parent only coordinates them
over pipes (JSON lines on each child's stdin and stdout) and sleeps in ``select`` while they
run, so it does not steal one of the machine's cores from what it measures.

A :class:`Link` decides where a process runs and which address reaches it. The default
:class:`LoopbackLink` runs everything here on 127.0.0.1; a link backed by the network emulator
(``rlbridge.netem``) can run side ``"a"`` (servers, receivers, listeners) and side ``"b"``
(clients, senders) in two namespaces without the benchmarks changing.

The parent terminates (then kills) every child it spawned when the run ends, also on an
exception; the children bound themselves too (:mod:`rlbridge.bench.child`).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import select
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import IO, Any, Protocol

from rlbridge.bench.base import BenchError, Params, Side

CLK_TCK = os.sysconf("SC_CLK_TCK")
#: Seconds a worker may take to start and report ``ready`` (imports on a loaded machine).
STARTUP_S = 30.0


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
        """The child's process id (for ``/proc`` readings)."""
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
        """CPU seconds the child used since :meth:`mark_cpu`."""
        return cpu_seconds(self.pid) - self._cpu0

    def stderr_tail(self) -> str:
        """The end of the child's stderr, as a suffix for an error message (empty if none)."""
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

    def start(self, name: str, side: Side, module: str, role: str, params: Params, *,
              python_files: bool = False) -> Worker:
        """Start ``module.ROLES[role](params)`` on ``side``; do not wait for it.

        ``python_files``: rlbridge's compiled modules run as their ``.py`` files in the worker
        (``RLBRIDGE_PURE_PYTHON``, rlbridge/_compiled.py), for a role that wraps their
        functions with probes (a compiled module's calls do not see the wrappers).
        """
        pure = "import os; os.environ['RLBRIDGE_PURE_PYTHON'] = '1'; " if python_files else ""
        argv = [sys.executable, "-c", pure + "from rlbridge.bench.child import worker_main; "
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
        """Stop every worker, the last started first."""
        for worker in reversed(self._workers):
            worker.stop()
        self._workers.clear()

    def __enter__(self) -> ProcessGroup:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def start_server(group: ProcessGroup, **config: Any) -> tuple[Worker, str, int]:
    """A server on side ``"a"``; returns it, the address clients use, and its port."""
    host = group.link.address("a")
    worker, ready = group.spawn("server", "a", "rlbridge.bench.child", "server",
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
        """CPU seconds process ``name`` spent per million values received."""
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


def rlbridge_flow(group: ProcessGroup, module: str, params: Params, timeout: float,
                  *, python_files: bool = False, **server_config: Any) -> Flow:
    """One stream through a server: the ``publisher`` and ``subscriber`` roles of ``module``
    (``bench latency``'s, or the probed ones of ``latency --stages``) on side ``"b"``, the
    server on side ``"a"``; CPU of the processes ``publisher``, ``server`` and ``subscriber``.
    ``python_files``: the SDK processes run the value path's Python files, not compiled."""
    server, host, port = start_server(group, **server_config)
    common: Params = {"host": host, "port": port, **params}
    sub = group.start("subscriber", "b", module, "subscriber", common, python_files=python_files)
    pub = group.start("publisher", "b", module, "publisher", common, python_files=python_files)
    for worker in (sub, pub):  # started together; the publisher waits for "go" anyway
        worker.expect("ready", STARTUP_S)
    return run_flow(pub, sub, [pub, server, sub], timeout)
