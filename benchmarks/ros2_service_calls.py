"""Service call round trips through rlbridge next to rclpy calling the same service directly.

Run: ``.venv/bin/python benchmarks/ros2_service_calls.py [--calls 200] [--rounds 5]``
(needs the ``ros2`` extra). Three processes on this host, ROS discovery kept on loopback
(``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, domain 66): a plain rclpy node serving
``std_srvs/SetBool`` (tests/adapters/ros2_reach_peer.py), ``rlbridge serve --adapter ros2``,
and this process, which alternates rounds of (a) an rclpy client calling the service (the
baseline: what a ROS node pays) and (b) ``Bridge.call`` through the server over TCP. Prints
a Markdown table of the medians and p99 of each round kind, pooled, and their ratio.
"""

from __future__ import annotations

import argparse
import functools
import os
import re
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PEER = ROOT / "tests" / "adapters" / "ros2_reach_peer.py"
SERVING = re.compile(r"rlbridge listening on [^ ]+ port (\d+) ")


def environment() -> dict[str, str]:
    env = {**os.environ, "ROS_DOMAIN_ID": "66", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "PYTHONUNBUFFERED": "1"}
    env.pop("ROS_STATIC_PEERS", None)
    return env


def _set(done: threading.Event, _future: object) -> None:
    done.set()


def rclpy_rounds(calls: int) -> object:
    """An rclpy client node in this process; returns a function timing ``calls`` calls."""
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_srvs.srv import SetBool

    context = Context()
    context.init(args=[], domain_id=66)
    node = Node("bench_rclpy_client", context=context)
    client: Any = node.create_client(SetBool, "/reach/set_bool")
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    if not client.wait_for_service(timeout_sec=30):
        raise SystemExit("the rclpy peer's service never appeared")

    def run() -> list[float]:
        out = []
        for i in range(calls):
            done = threading.Event()
            start = time.perf_counter()
            future = client.call_async(SetBool.Request(data=bool(i % 2)))
            future.add_done_callback(functools.partial(_set, done))
            if not done.wait(5):
                raise SystemExit("rclpy call timed out")
            out.append(time.perf_counter() - start)
        return out

    return run


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--calls", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    os.environ.update(environment())
    env = environment()
    peer = subprocess.Popen([sys.executable, str(PEER), "serve"], env=env, text=True,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    server = subprocess.Popen([sys.executable, "-m", "rlbridge.cli", "--log-level", "info",
                               "serve", "--port", "0", "--adapter", "ros2", "--node-name",
                               "bench_bridge"], env=env, text=True, stderr=subprocess.PIPE,
                              stdout=subprocess.DEVNULL)
    try:
        assert peer.stdout is not None
        assert server.stderr is not None
        peer.stdout.readline()  # "ready"
        port = None
        for line in server.stderr:
            match = SERVING.search(line)
            if match:
                port = int(match.group(1))
                break
        assert port is not None, "the server did not start"
        threading.Thread(target=server.stderr.read, daemon=True).start()
        from rlbridge.client.bridge import Bridge

        direct = rclpy_rounds(args.calls)
        with Bridge.connect("127.0.0.1", port, name="bench", reconnect=False) as bridge:
            bridge.call("/reach/set_bool", "std_srvs/srv/SetBool", {"data": True}, timeout=30)

            def bridged() -> list[float]:
                out = []
                for i in range(args.calls):
                    start = time.perf_counter()
                    bridge.call("/reach/set_bool", "std_srvs/srv/SetBool",
                                {"data": bool(i % 2)})
                    out.append(time.perf_counter() - start)
                return out

            pooled: dict[str, list[float]] = {"rclpy client (baseline)": [], "Bridge.call": []}
            for _ in range(args.rounds):  # interleaved, so both see the same machine load
                pooled["rclpy client (baseline)"] += direct()  # type: ignore[operator]
                pooled["Bridge.call"] += bridged()
    finally:
        if peer.stdin is not None:
            peer.stdin.close()
        server.terminate()
        peer.wait(10)
        server.wait(10)
    base = statistics.median(pooled["rclpy client (baseline)"])
    print(f"| {args.rounds} x {args.calls} calls each | median ms | p99 ms | median / baseline |")
    print("|---|---|---|---|")
    for name, times in pooled.items():
        p99 = statistics.quantiles(times, n=100)[98]
        print(f"| {name} | {statistics.median(times) * 1e3:.3f} | {p99 * 1e3:.3f} | "
              f"{statistics.median(times) / base:.2f} |")


if __name__ == "__main__":
    main()
