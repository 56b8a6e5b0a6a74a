"""The SDK receive thread's CPU per wake-up, without the wake-up: two source trees, interleaved.

    git worktree add --detach /tmp/rlbridge-base <commit>
    .venv/bin/python benchmarks/recv_path_ab.py --a /tmp/rlbridge-base/src --b src \
        [--repeats 6] [--channels 10] [--wakeups 20000]

The shape of ``rlbridge bench cpu`` as the receive thread sees it: one bundle datagram per tick
carrying one value for each of ``--channels`` channels. A real
:class:`~rlbridge.client.session.connection.Connection` (not opened) gets a UDP socket connected to
a
socket of this script, which plays the server; each tick sends one real datagram, then times
(``time.thread_time``) what the receive thread does once ``poll`` says it is readable: the
``poll`` itself, ``Receiver._receive_datagrams`` (``recv``, decode, gather), ``_flush_values``
(every channel's ``IncomingChannel.deliver``: sequence check, measurements, ring write) and
``_tick`` (watchdog, heartbeat, next deadline). The reads of the channels are not timed.

What this leaves out is the wake-up itself (the scheduler's switch into the thread, about a
fifth of the thread's CPU in ``perf`` on this VM) and the GIL hand-offs: measured whole by
``benchmarks/sdk_send_ab.py`` (``recv_thread``). This one is steadier, for comparing code.
Each tree runs in its own process (``PYTHONPATH``), alternately (ABBA...); prints every run,
the medians (µs per wake-up and per value) and B/A. Every run checks that every value arrived
in its channel with no gap.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import select
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

F64 = "std_msgs/msg/Float64"
TOKEN = 0x5EED


def client(channels: int, wakeups: int) -> None:
    """One measurement with the tree on ``PYTHONPATH``; prints one JSON line."""
    from rlbridge.client.channels.incoming import IncomingChannel
    from rlbridge.client.session.connection import Connection
    from rlbridge.client.session.receiver import Receiver
    from rlbridge.wire import Bundle, PacketCodec, Value
    from rlbridge.wire.link import LinkMonitor

    server = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    server.bind(("127.0.0.1", 0))
    conn = Connection("127.0.0.1", server.getsockname()[1], name="recv-ab", nodelay=True,
                      control="tcp", timeout=5.0)
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.connect(server.getsockname())
    server.connect(udp.getsockname())
    conn.udp = udp
    link = LinkMonitor(time.monotonic_ns(), 3_600_000_000_000)  # no heartbeat is due
    link.make_heartbeat(time.monotonic_ns())
    conn.link = link
    inboxes = {ch: IncomingChannel(ch, f"/ab/c{ch}", F64, None, transport="udp", blocking=True,
                                   buffer_size=256) for ch in range(channels)}

    def on_values(ch: int, first_seq: int, stamps: list[int], values: list[Any]) -> None:
        inbox = inboxes.get(ch)  # as Bridge._on_values does
        if inbox is not None:
            inbox.deliver(first_seq, stamps, values)

    conn.on_values = on_values
    receiver = Receiver(conn, 0, [], conn._wake_r)
    poller = select.poll()
    poller.register(udp, select.POLLIN)
    queued = select.poll()
    queued.register(udp, select.POLLIN)
    # The tree before the zero-timeout "queued" poll took (sock, token) only.
    takes_queued = len(inspect.signature(receiver._receive_datagrams).parameters) == 3
    codec = PacketCodec()
    wait, clock = poller.poll, time.thread_time
    spent = 0.0
    for seq in range(wakeups):
        now = time.time_ns()
        server.send(codec.encode_datagram(
            Bundle([Value(ch, seq, now, float(seq)) for ch in range(channels)]), TOKEN))
        t0 = clock()
        wait(None)
        if takes_queued:
            receiver._receive_datagrams(udp, TOKEN, queued.poll)
        else:
            receiver._receive_datagrams(udp, TOKEN)  # type: ignore[call-arg]
        receiver._flush_values()
        receiver._tick(link, 0)
        spent += clock() - t0
        for inbox in inboxes.values():
            inbox.read_many()
    values = sum(inbox.health().values for inbox in inboxes.values())
    lost = sum(inbox.lost for inbox in inboxes.values())
    for sock in (server, udp, conn._wake_r, conn._wake_w):
        sock.close()
    print(json.dumps({"spent": spent, "values": values, "lost": lost}), flush=True)


def run_one(tree: str, args: argparse.Namespace) -> dict[str, float]:
    env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve()))
    out = subprocess.run(
        [sys.executable, __file__, "client", "--channels", str(args.channels), "--wakeups",
         str(args.wakeups)], env=env, capture_output=True, text=True, timeout=600, check=True)
    raw = json.loads(out.stdout.strip().splitlines()[-1])
    expected = args.channels * args.wakeups
    if raw["values"] != expected or raw["lost"]:
        raise SystemExit(f"run lost values: {raw} (expected {expected})")
    per_wakeup = raw["spent"] / args.wakeups * 1e6
    return {"wakeup": per_wakeup, "value": per_wakeup / args.channels}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd")
    c = sub.add_parser("client")
    for a in (p, c):
        for flag, default in (("--channels", 10), ("--wakeups", 20000)):
            a.add_argument(flag, type=int, default=default)
    for arm, tree in (("--a", "the baseline tree"), ("--b", "the tree under test")):
        p.add_argument(arm, required=True, help=f"src/ of {tree}")
    p.add_argument("--repeats", type=int, default=6)
    if len(sys.argv) > 1 and sys.argv[1] == "client":
        ca = c.parse_args(sys.argv[2:])
        client(ca.channels, ca.wakeups)
        return
    args = p.parse_args()
    runs: dict[str, list[dict[str, float]]] = {"A": [], "B": []}
    for i in range(args.repeats):
        for arm in ("AB" if i % 2 == 0 else "BA"):
            us = run_one(args.a if arm == "A" else args.b, args)
            runs[arm].append(us)
            print(f"{arm} wakeup={us['wakeup']:.2f} value={us['value']:.2f}", flush=True)
    print(f"\nmedians, CPU us ({args.repeats} runs each, {args.channels} channels, "
          f"{args.wakeups} wake-ups):")
    print(f"{'':14}{'A':>8}{'B':>8}{'B/A':>7}")
    for k, label in (("wakeup", "per wake-up"), ("value", "per value")):
        med_a = statistics.median(r[k] for r in runs["A"])
        med_b = statistics.median(r[k] for r in runs["B"])
        print(f"{label:14}{med_a:8.2f}{med_b:8.2f}{med_b / med_a:7.2f}")


if __name__ == "__main__":
    main()
