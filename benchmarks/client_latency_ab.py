"""One-way latency through the server, two SDK source trees, interleaved (ABBA...).

    git worktree add /tmp/rlbridge-base <commit>    # or copy its src/ anywhere
    .venv/bin/python benchmarks/client_latency_ab.py --a /tmp/rlbridge-base/src --b src \\
        [--repeats 8] [--values 2000] [--idle park]

One ``ServerThread`` (tree B) for the whole run. Each run starts a subscriber and a publisher
process with ``PYTHONPATH`` set to one tree: the publisher writes ``time.time_ns()`` at 1 kHz
on a UDP channel (``Bridge.connect(idle=...)``), the subscriber blocks in ``read`` and takes
``time.time_ns()`` minus the value; the first 50 are dropped. A and B alternate, so a change in
the machine's load hits both alike; prints every run's p50 and p90, the medians of p50 and B/A
(``benchmarks/ab.py``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
import time

CLIENT = r"""
import json, sys, time
from rlbridge import Bridge, Tuning
role, topic, idle = sys.argv[1], sys.argv[3], sys.argv[5]
port, count = int(sys.argv[2]), int(sys.argv[4])
b = Bridge.connect("127.0.0.1", port, name=f"ab-{role}",
                   tuning=Tuning(idle=tuple(idle.split("/")) if "/" in idle else idle))
if role == "pub":
    out = b.publish(topic, "std_msgs/msg/Int64", "data", transport="udp")
    time.sleep(1.0)
    start = time.monotonic_ns()
    for i in range(count):
        delay = start + i * 1_000_000 - time.monotonic_ns()
        if delay > 0:
            time.sleep(delay / 1e9)
        out.write(time.time_ns())
    time.sleep(0.3)
else:
    ch = b.subscribe(topic, "std_msgs/msg/Int64", "data", transport="udp", blocking=True,
                     buffer_size=1024)
    print("ready", flush=True)
    lat, t0 = [], time.monotonic()
    while len(lat) < count and time.monotonic() - t0 < count / 1000 + 8:
        try:
            value = ch.read(0.2)
        except TimeoutError:
            continue
        lat.append(time.time_ns() - value)
    kept = sorted(x / 1000 for x in lat[50:])
    print(json.dumps({"p50": kept[len(kept) // 2], "p90": kept[int(len(kept) * 0.9)],
                      "n": len(kept)}), flush=True)
b.close()
"""
SERVER = ("import sys\nfrom rlbridge.server import ServerThread\n"
          "with ServerThread() as s:\n    print(s.port, flush=True)\n    sys.stdin.read()\n")


def one(tree: str, port: int, topic: str, values: int, idle: str) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": tree}
    args = [str(port), topic, str(values), idle]
    sub = subprocess.Popen([sys.executable, "-c", CLIENT, "sub", *args], env=env,
                           stdout=subprocess.PIPE, text=True)
    try:
        assert sub.stdout is not None
        if sub.stdout.readline().strip() != "ready":
            raise SystemExit("the subscriber did not start")
        subprocess.run([sys.executable, "-c", CLIENT, "pub", *args], env=env, timeout=120,
                       check=True)
        result: dict[str, float] = json.loads(sub.stdout.readline())
        return result
    finally:
        sub.wait(30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--a", required=True, help="source tree A (its src/)")
    parser.add_argument("--b", required=True, help="source tree B (its src/)")
    parser.add_argument("--repeats", type=int, default=8)
    parser.add_argument("--values", type=int, default=2000)
    parser.add_argument("--idle", default="park")
    args = parser.parse_args()
    trees = {"A": os.path.abspath(args.a), "B": os.path.abspath(args.b)}
    if not __package__:  # run as a file: the checkout's root makes `benchmarks` importable
        sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from benchmarks.ab import interleave

    server = subprocess.Popen([sys.executable, "-c", SERVER], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": trees["B"]})
    assert server.stdout is not None
    assert server.stdin is not None
    port = int(server.stdout.readline())
    runs = itertools.count()

    def run(tree: str) -> tuple[float, str]:
        got = one(tree, port, f"/ab_{next(runs)}", args.values, args.idle)
        return got["p50"], f"p90 {got['p90']:9.1f} us  load {os.getloadavg()[0]:.1f}"

    try:
        print(f"idle={args.idle}, {args.repeats} runs each, {time.strftime('%Y-%m-%d %H:%M')}")
        interleave(run, trees["A"], trees["B"], args.repeats, digits=1, unit="us p50")
    finally:
        server.stdin.close()
        server.wait(10)


if __name__ == "__main__":
    main()
