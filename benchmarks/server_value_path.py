"""The server's Python per value, without the system calls: two source trees, interleaved.

    .venv/bin/python benchmarks/server_value_path.py --a /tmp/rlbridge-base/src --b src \
        [--repeats 5] [--channels 10] [--bundles 20000]

``server_path_ab.py`` measures the whole server process over real sockets, where the kernel's
share (the event loop's receive, one ``sendto`` per tick) is most of the CPU and the machine's
load moves every figure. This one isolates what Python code changes can change: the real server
objects (``UdpEndpoint``, ``SessionRegistry``, sessions, bindings, the in-process bus,
``UdpSink``) on a real event loop (uvloop, as the server runs), fed prebuilt datagrams by direct
``datagram_received`` calls, with a transport whose ``sendto`` only counts the bytes. One
session opens ``--channels`` publish channels and subscribes to the same topics over UDP (the
shape of ``bench cpu``), then gets ``--bundles`` datagrams of one ``Value`` per channel
(``--single``: one ``Value`` per datagram); after each datagram the loop runs one iteration, so
the corked values leave as one bundle per tick as on a real server. The figure is the thread CPU
time per value (in and out: one value published and sent back). A and B alternate in fresh
processes (ABBA...).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any


class _CountingTransport(asyncio.DatagramTransport):
    """A datagram transport that sends nothing: the system call is not what is measured."""

    def __init__(self) -> None:
        super().__init__()
        self.datagrams = 0
        self.bytes = 0

    def sendto(self, data: Any, addr: Any = None) -> None:
        self.datagrams += 1
        self.bytes += len(data)

    def is_closing(self) -> bool:
        return False

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return default


async def _run(channels: int, bundles: int, single: bool) -> tuple[float, int, int]:
    from rlbridge.adapters.inproc import InProcessBus
    from rlbridge.server.config import ServerConfig
    from rlbridge.server.context import ServerContext
    from rlbridge.server.handoff import LoopHandoff
    from rlbridge.server.registry import SessionRegistry
    from rlbridge.server.udp import UdpEndpoint
    from rlbridge.wire import PROTOCOL_VERSION, Bundle, Hello, PacketCodec, TopicConnect, Value
    from rlbridge.wire.codec import FLAG_BUNDLES

    loop = asyncio.get_running_loop()
    codec = PacketCodec()
    # A minute between heartbeats: building the datagrams takes a while without the loop.
    cfg = ServerConfig(port=0, heartbeat_ms=60_000, timeout_ms=600_000)
    ctx = ServerContext(cfg, InProcessBus(), codec, loop, LoopHandoff(loop))
    registry = SessionRegistry(ctx)
    endpoint = UdpEndpoint(registry)
    transport = _CountingTransport()
    endpoint.connection_made(transport)
    addr = ("127.0.0.1", 40000)
    flags = 0 if single else FLAG_BUNDLES
    endpoint.datagram_received(codec.encode_datagram(Hello(PROTOCOL_VERSION, "vp"), 0, flags),
                               addr)
    session = next(iter(registry))
    token = session.token
    f64 = "std_msgs/msg/Float64"
    for c in range(channels):
        for connect in (TopicConnect(1000 + c, "subscribe", f"/vp/c{c}", f64, transport="udp"),
                        TopicConnect(1 + c, "publish", f"/vp/c{c}", f64, transport="udp")):
            endpoint.datagram_received(codec.encode_datagram(connect, token, flags), addr)
    await asyncio.sleep(0)
    stamp = time.time_ns()
    if single:
        data = [[codec.encode_datagram(Value(1 + c, i, stamp, float(i)), token, flags)
                 for c in range(channels)] for i in range(bundles)]
    else:
        data = [[codec.encode_datagram(Bundle([Value(1 + c, i, stamp, float(i))
                                               for c in range(channels)]), token, flags)]
                for i in range(bundles)]
    receive = endpoint.datagram_received
    sent0 = transport.datagrams
    t0 = time.thread_time()
    for tick in data:
        for datagram in tick:
            receive(datagram, addr)
        await asyncio.sleep(0)
    cpu = time.thread_time() - t0
    out = sum(b.values_out for b in session.outbound.values())
    if session.closed or set(ctx.counters) != {"sessions_opened"}:
        raise RuntimeError(f"the session did not take every value: {ctx.counters}")
    session.close("done")
    return cpu, out, transport.datagrams - sent0


def child(args: argparse.Namespace) -> None:
    from rlbridge.server.app import new_event_loop

    loop = new_event_loop()  # uvloop, as the server runs
    try:
        cpu, out, datagrams = loop.run_until_complete(
            _run(args.channels, args.bundles, args.single))
    finally:
        loop.close()
    print(f"{cpu * 1e6 / max(1, out):.4f} {out} {datagrams}")


def measure(tree: str, args: argparse.Namespace) -> tuple[float, int, int]:
    env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve()))
    cmd = [sys.executable, __file__, "--child", "--channels", str(args.channels),
           "--bundles", str(args.bundles), *(["--single"] if args.single else [])]
    us, out, datagrams = subprocess.run(cmd, env=env, check=True, capture_output=True,
                                        text=True).stdout.split()
    return float(us), int(out), int(datagrams)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channels", type=int, default=10)
    parser.add_argument("--bundles", type=int, default=20000)
    parser.add_argument("--single", action="store_true", help="one Value per datagram")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    if not __package__:  # run as a file: the checkout's root makes `benchmarks` importable
        sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from benchmarks.ab import interleave, tree_arguments

    tree_arguments(parser, repeats=5)
    args = parser.parse_args()
    if args.child:
        child(args)
        return
    if not args.a or not args.b:
        parser.error("--a and --b are required")

    def run(tree: str) -> tuple[float, str]:
        us, out, datagrams = measure(tree, args)
        return us, f" values out {out}  datagrams out {datagrams}"

    interleave(run, args.a, args.b, args.repeats, digits=3)

if __name__ == "__main__":
    main()
