"""SDK CPU per value, send side split from receive side: two source trees, interleaved.

    git worktree add /tmp/rlbridge-base <commit>    # or copy its src/ anywhere
    .venv/bin/python benchmarks/sdk_send_ab.py --a /tmp/rlbridge-base/src --b src \
        [--repeats 6] [--channels 10] [--rate 1000] [--seconds 5] [--transport tcp]

The shape of ``rlbridge bench cpu`` (one client, ``--channels`` channels at ``--rate`` Hz, UDP
or ``--transport tcp`` (the send round's frames, cut by count and bytes),
buffered writes and one ``Bridge.send()`` per tick, read back with ``read_many``), but the
client runs with ``PYTHONPATH`` set to tree A or B, in turn (ABBA...), against one
``rlbridge serve`` of the installed tree, and it splits the SDK's CPU finer than the bench:

* ``write``: the loop's thread CPU inside the ``write`` calls of a tick;
* ``send()``: inside ``Bridge.send()`` (the doorbell);
* ``send thread``: the ``rlbridge-send`` thread;
* ``read_many`` and ``receive thread``: the reading side, for the total.

The loop's CPU is ``time.thread_time`` (CLOCK_THREAD_CPUTIME_ID) around each group of calls,
the I/O threads' their own CPU-time clocks (``pthread_getcpuclockid``), so
the figures are CPU time, robust to the machine's load; each reading adds its own system
call to the figure it brackets, the same in both trees. Prints every run, the medians
(µs per value read back) and B/A.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Literal

KEYS = ("write", "send_call", "send_thread", "read_many", "recv_thread", "sdk", "send_side")
F64 = "std_msgs/msg/Float64"


def _thread_clock(name: str) -> int:
    """The CPU-time clock of this process's thread ``name`` (nanosecond resolution)."""
    for thread in threading.enumerate():
        if thread.name == name and thread.ident is not None:
            return time.pthread_getcpuclockid(thread.ident)
    raise RuntimeError(f"no thread {name!r}")


def client(port: int, channels: int, rate: float, seconds: float,
           transport: Literal["udp", "tcp"] = "udp") -> None:
    """One SDK client (the tree on PYTHONPATH); prints one JSON line of CPU seconds."""
    from rlbridge.client.bridge import Bridge

    b = Bridge.connect("127.0.0.1", port, name="sdk-ab", timeout=30)
    topics = [f"/ab/c{i}" for i in range(channels)]
    inboxes = [b.subscribe(t, F64, transport=transport, buffer_size=256) for t in topics]
    outs = [b.publish(t, F64, transport=transport, through_buffer=True) for t in topics]
    time.sleep(0.5)
    thread_time, monotonic, sleep = time.thread_time, time.monotonic, time.sleep
    recv_clock, send_clock = _thread_clock("rlbridge-recv"), _thread_clock("rlbridge-send")
    cpu = time.clock_gettime
    ticks = int(seconds * rate)
    w = s = r = 0.0
    received = 0
    recv0, send0 = cpu(recv_clock), cpu(send_clock)
    start = monotonic()
    for i in range(ticks):
        delay = start + i / rate - monotonic()
        if delay > 0:
            sleep(delay)
        value = float(i)
        t0 = thread_time()
        for out in outs:
            out.write(value)
        t1 = thread_time()
        b.send()
        t2 = thread_time()
        for inbox in inboxes:
            received += len(inbox.read_many())
        t3 = thread_time()
        w += t1 - t0
        s += t2 - t1
        r += t3 - t2
    end = monotonic() + 1.0
    while received < ticks * channels and monotonic() < end:
        sleep(0.001)
        t0 = thread_time()
        for inbox in inboxes:
            received += len(inbox.read_many())
        r += thread_time() - t0
    print(json.dumps({"write": w, "send_call": s, "read_many": r,
                      "send_thread": cpu(send_clock) - send0,
                      "recv_thread": cpu(recv_clock) - recv0,
                      "sent": ticks * channels, "received": received,
                      "unsent": sum(out.pending() + out.statistics().overwritten for out in outs),
                      "gaps": sum(inbox.lost for inbox in inboxes),
                      "in_overwritten": sum(i.statistics().overwritten for i in inboxes),
                      "reconnects": b.reconnects,
                      "send_errors": getattr(b._sender, "send_errors", -1),
                      "values_sent": getattr(b._sender, "values_sent", -1)}), flush=True)
    b.close()


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def run_one(tree: str, port: int, args: argparse.Namespace) -> dict[str, float]:
    env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve()))
    out = subprocess.run(
        [sys.executable, __file__, "client", "--port", str(port), "--channels",
         str(args.channels), "--rate", str(args.rate), "--seconds", str(args.seconds),
         "--transport", args.transport],
        env=env, capture_output=True, text=True, timeout=args.seconds + 60, check=True)
    raw = json.loads(out.stdout.strip().splitlines()[-1])
    got = max(1, int(raw["received"]))
    us = {k: float(raw[k]) / got * 1e6 for k in ("write", "send_call", "send_thread",
                                                  "read_many", "recv_thread")}
    us["send_side"] = us["write"] + us["send_call"] + us["send_thread"]
    us["sdk"] = us["send_side"] + us["read_many"] + us["recv_thread"]
    us["delivered"] = int(raw["received"]) / int(raw["sent"])
    if us["delivered"] < 0.999:  # where: unsent, overwritten in the reader's ring, gaps
        print(f"  run lost values: {raw}", flush=True)
    return us


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd")
    c = sub.add_parser("client")
    c.add_argument("--port", type=int, required=True)
    for a in (p, c):
        a.add_argument("--channels", type=int, default=10)
        a.add_argument("--rate", type=float, default=1000.0)
        a.add_argument("--seconds", type=float, default=5.0)
        a.add_argument("--transport", choices=("udp", "tcp"), default="udp")
    p.add_argument("--a", required=True, help="src/ of the baseline tree")
    p.add_argument("--b", required=True, help="src/ of the tree under test")
    p.add_argument("--repeats", type=int, default=6)
    if len(sys.argv) > 1 and sys.argv[1] == "client":
        ca = c.parse_args(sys.argv[2:])
        client(ca.port, ca.channels, ca.rate, ca.seconds, ca.transport)
        return
    args = p.parse_args()
    port = _free_port()
    server = subprocess.Popen(
        [str(Path(sys.executable).with_name("rlbridge")), "serve", "--host", "127.0.0.1",
         "--port", str(port), "--timeout-ms", "5000"], stderr=subprocess.DEVNULL)
    runs: dict[str, list[dict[str, float]]] = {"A": [], "B": []}
    try:
        time.sleep(2.0)
        for i in range(args.repeats):
            for arm in ("AB" if i % 2 == 0 else "BA"):
                us = run_one(args.a if arm == "A" else args.b, port, args)
                runs[arm].append(us)
                print(f"{arm} " + " ".join(f"{k}={us[k]:.2f}" for k in KEYS)
                      + f" delivered={us['delivered']:.4f}", flush=True)
    finally:
        server.terminate()
        server.wait(10)
    print(f"\nmedians, CPU us per value read back ({args.repeats} runs each, "
          f"{args.channels} {args.transport} channels x {args.rate:g} Hz x {args.seconds:g} s):")
    print(f"{'':14}{'A':>8}{'B':>8}{'B/A':>7}")
    for k in KEYS:
        med_a = statistics.median(r[k] for r in runs["A"])
        med_b = statistics.median(r[k] for r in runs["B"])
        ratio = med_b / med_a if med_a else float("nan")
        print(f"{k:14}{med_a:8.2f}{med_b:8.2f}{ratio:7.2f}")


if __name__ == "__main__":
    main()
