"""Server CPU per value (in + out), one value per datagram: two source trees, interleaved.

    git worktree add /tmp/rlbridge-base <commit>    # or copy its src/ anywhere
    .venv/bin/python benchmarks/server_path_ab.py --a /tmp/rlbridge-base/src --b src \
        [--repeats 6] [--sessions 10] [--rate 100] [--seconds 4]

Each repeat starts a fresh ``rlbridge serve`` with ``PYTHONPATH`` set to one tree, opens
``--sessions`` protocol-level UDP sessions (the ``bench load`` raw clients: 10 channels each,
publishing and subscribing to their own topics) in this process, writes every channel at
``--rate`` Hz for ``--seconds``, and divides the server's CPU time (``/proc/<pid>/stat``, user +
system) by the values that came back. A and B alternate (ABBA...), so a change in the machine's
load hits both alike; prints every run, the medians and B/A. A rate the server sustains keeps the
figure a cost, not a queue: check the delivered fraction is ~1.
"""

from __future__ import annotations

import argparse
import os
import selectors
import socket
import subprocess
import sys
import time
from pathlib import Path

from rlbridge.bench.load_raw import _RawSession
from rlbridge.wire import PacketCodec

SERVE = [str(Path(sys.executable).with_name("rlbridge")), "serve", "--host", "127.0.0.1",
         "--heartbeat-ms", "500", "--timeout-ms", "5000"]


def cpu_s(pid: int) -> tuple[float, float]:
    """User and system CPU seconds of ``pid``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    tick = os.sysconf("SC_CLK_TCK")
    return int(fields[11]) / tick, int(fields[12]) / tick


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_listening(port: int, timeout: float = 60.0) -> None:
    """Until the server accepts on ``port`` (a loaded machine may take seconds to start it)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def measure(tree: str, args: argparse.Namespace) -> tuple[float, float, float]:
    """(CPU µs per value, of which system µs, fraction delivered) for one server run."""
    port = free_port()
    env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve()))
    server = subprocess.Popen([*SERVE, "--port", str(port)], env=env, stderr=subprocess.DEVNULL)
    sessions: list[_RawSession] = []
    try:
        wait_listening(port)  # the server's start (imports) is not measured
        params = {"host": "127.0.0.1", "port": port, "channels": 10}
        codec = PacketCodec()
        sessions = [_RawSession(params, i, ["m"], codec) for i in range(args.sessions)]
        with selectors.DefaultSelector() as sel:
            for s in sessions:
                sel.register(s.sock, selectors.EVENT_READ, s)

            def run(seconds: float) -> None:
                start, ticks = time.monotonic(), 0
                while time.monotonic() - start < seconds:
                    for s in sessions:
                        s.write_all(time.time())
                    ticks += 1
                    deadline = start + ticks / args.rate
                    while (left := deadline - time.monotonic()) > 0:
                        for key, _ in sel.select(left):
                            key.data.drain()
                end = time.monotonic() + 0.5  # let the last values come back
                while time.monotonic() < end:
                    for key, _ in sel.select(0.05):
                        key.data.drain()

            run(1.0)  # warm-up
            got0, sent0 = sum(s.received() for s in sessions), sum(s.sent for s in sessions)
            user0, sys0 = cpu_s(server.pid)
            run(args.seconds)
            user1, sys1 = cpu_s(server.pid)
            got = sum(s.received() for s in sessions) - got0
            sent = sum(s.sent for s in sessions) - sent0
        n = max(1, got)
        return ((user1 - user0 + sys1 - sys0) * 1e6 / n, (sys1 - sys0) * 1e6 / n,
                got / max(1, sent))
    finally:
        for s in sessions:
            s.close()
        server.terminate()
        server.wait(10)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--a", required=True, help="src/ directory of the baseline")
    parser.add_argument("--b", required=True, help="src/ directory of the candidate")
    parser.add_argument("--repeats", type=int, default=6)
    parser.add_argument("--sessions", type=int, default=10)
    parser.add_argument("--rate", type=float, default=100.0)
    parser.add_argument("--seconds", type=float, default=4.0)
    args = parser.parse_args()

    if not __package__:  # run as a file: the checkout's root makes `benchmarks` importable
        sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from benchmarks.ab import interleave

    def run(tree: str) -> tuple[float, str]:
        us, sys_us, delivered = measure(tree, args)
        return us, f"(system {sys_us:5.1f})  delivered {delivered:.3f}"

    interleave(run, args.a, args.b, args.repeats, digits=1)


if __name__ == "__main__":
    main()
