"""Channel policies on a live server, over real loopback sockets.

The latest-value tests stall a real TCP reader (a client that stops reading, with a small
receive buffer), so the server's kernel send queue fills: what is measured is the kernel's
state (``rlbridge.tcpstate``), not a model of it.
"""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from rlbridge.server import ServerThread
from rlbridge.server.handoff import LoopHandoff
from rlbridge.wire import (
    PROTOCOL_VERSION,
    Batch,
    ConnectAck,
    FrameDecoder,
    Hello,
    Malformed,
    PacketCodec,
    Stats,
    TopicAck,
    TopicConnect,
    Value,
)
from waiting import wait_until

STR = "std_msgs/msg/String"
F64 = "std_msgs/msg/Float64"
PAD = "x" * 2000
N = 300
WAIT = 10.0
#: The stalled reader sends no heartbeats: on a loaded machine the default test watchdog
#: (5 s) could end its session mid-test, which is not what these tests are about.
STALLED_WATCHDOG_MS = 60_000


class StalledReader:
    """A TCP subscriber with a tiny receive window that reads only when told to."""

    def __init__(self, port: int) -> None:
        self.codec = PacketCodec()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # before connect
        self.sock.connect(("127.0.0.1", port))
        self.sock.settimeout(WAIT)
        self.decoder = FrameDecoder(self.codec)
        self.values: list[tuple[int, Any]] = []

    def send(self, *packets: Any) -> None:
        buf = bytearray()
        for packet in packets:
            self.codec.encode_frame_into(packet, buf)
        self.sock.sendall(buf)

    def expect(self, cls: type) -> Any:
        while True:
            for packet in self.decoder.feed(self.sock.recv(1 << 16)):
                if isinstance(packet, cls):
                    return packet

    def subscribe(self, topic: str, latest: bool) -> None:
        self.send(Hello(PROTOCOL_VERSION, f"stalled-{latest}"))
        self.expect(ConnectAck)
        self.send(TopicConnect(1, "subscribe", topic, STR, transport="tcp", latest=latest))
        self.expect(TopicAck)

    def drain_until(self, last: str) -> None:
        """Read everything until the value ``last`` arrived; record (seq, value)."""
        def arrived() -> bool:
            if self.values and self.values[-1][1] == last:
                return True
            for packet in self.decoder.feed(self.sock.recv(1 << 16)):
                assert not isinstance(packet, Malformed)
                if isinstance(packet, Value):
                    self.values.append((packet.seq, packet.value))
                elif isinstance(packet, Batch):
                    self.values.extend(
                        (packet.first_seq + i, v) for i, v in enumerate(packet.values))
            return False

        wait_until(arrived, lambda: f"{last[:8]!r} ({len(self.values)} values came)",
                   timeout=WAIT, interval=0)

    def stats(self) -> dict[str, Any]:
        self.send(Stats())

        def answer() -> dict[str, Any] | None:  # values and heartbeats before it are skipped
            for packet in self.decoder.feed(self.sock.recv(1 << 16)):
                if isinstance(packet, Stats):
                    return packet.body["session"]["channels"]["1"]  # type: ignore[no-any-return]
            return None

        channel: dict[str, Any] = wait_until(answer, "the server's Stats answer", timeout=WAIT,
                                             interval=0)
        return channel

    def close(self) -> None:
        self.sock.close()


def _publish_burst(raw_tcp: Callable[..., Any], topic: str) -> list[str]:
    pub = raw_tcp()
    pub.hello("publisher")
    pub.send(TopicConnect(9, "publish", topic, STR, transport="tcp"))
    pub.expect(TopicAck)
    sent = [f"{i:04d}{PAD}" for i in range(N)]
    for i, value in enumerate(sent):  # one packet each: one middleware message each
        pub.send(Value(9, i, time.time_ns(), value))
    return sent


def _wait_server(srv: ServerThread, pred: Callable[[dict[str, Any]], bool]) -> dict[str, Any]:
    """Poll the server's own per-channel counters (through the session objects)."""
    seen: list[dict[str, Any]] = [{}]

    def counters() -> dict[str, Any] | None:
        registry = srv.server.registry
        assert registry is not None
        sessions = [s for s in list(registry) if s.outbound]
        chans = [o for s in sessions for o in list(s.outbound.values())]
        if not chans:
            return None
        seen[0] = chans[0].health(-1)
        return seen[0] if pred(seen[0]) else None

    found: dict[str, Any] = wait_until(counters, lambda: f"the server's counters (stuck at "
                                       f"{seen[0]})", interval=0.02)
    return found


def test_latest_tcp_channel_skips_the_backlog_of_a_stalled_reader(
        make_server: Callable[..., ServerThread], raw_tcp: Callable[..., Any]) -> None:
    srv = make_server(timeout_ms=STALLED_WATCHDOG_MS)
    reader = StalledReader(srv.port)
    try:
        reader.subscribe("/sp/latest", latest=True)
        sent = _publish_burst(lambda: raw_tcp(srv.port), "/sp/latest")
        # Every value was either written or overtaken; the last one may still wait for the
        # reader (or have been written already, if the socket drained in between).
        _wait_server(srv, lambda c: c["values"] + c["overtaken"] >= N - 1)
        reader.drain_until(sent[-1])
        counters = reader.stats()
    finally:
        reader.close()
    got = [v for _, v in reader.values]
    seqs = [s for s, _ in reader.values]
    assert got[-1] == sent[-1], "the newest value must arrive"
    assert counters["overtaken"] > 0, "the kernel queue filled, so values were overtaken"
    assert counters["values"] + counters["overtaken"] == N
    assert len(got) == counters["values"] < N
    assert seqs == list(range(len(seqs))), "overtaken values leave no sequence gap"
    assert got == sorted(got), "what arrives is in publication order"


def test_plain_tcp_channel_delivers_the_whole_backlog(
        make_server: Callable[..., ServerThread], raw_tcp: Callable[..., Any]) -> None:
    """The baseline of the test above: the same stall delivers every stale value."""
    srv = make_server(timeout_ms=STALLED_WATCHDOG_MS)
    reader = StalledReader(srv.port)
    try:
        reader.subscribe("/sp/plain", latest=False)
        sent = _publish_burst(lambda: raw_tcp(srv.port), "/sp/plain")
        reader.drain_until(sent[-1])
        counters = reader.stats()
    finally:
        reader.close()
    assert [v for _, v in reader.values] == sent
    assert counters["overtaken"] == 0


def _pub_sub(raw_tcp: Callable[..., Any], topic: str, **publish: Any) -> tuple[Any, Any]:
    """A raw subscriber (channel 1) and a raw publisher (channel 2, ``publish`` options)."""
    sub = raw_tcp()
    sub.hello("sub")
    sub.send(TopicConnect(1, "subscribe", topic, F64, transport="tcp"))
    sub.expect(TopicAck)
    pub = raw_tcp()
    pub.hello("pub")
    pub.send(TopicConnect(2, "publish", topic, F64, transport="tcp", **publish))
    pub.expect(TopicAck)
    return sub, pub


def test_inbound_policies_dedup_expire_and_keep_latest(
        server: ServerThread, raw_tcp: Callable[..., Any]) -> None:
    sub, pub = _pub_sub(raw_tcp, "/in/pol", max_age_ms=1000, latest=True)
    now = time.time_ns()
    old = now - 60_000_000_000
    pub.send(Batch(2, 0, [now, now, now], [1.0, 2.0, 3.0]))  # latest: only 3.0 published
    pub.send(Batch(2, 2, [now, now], [3.0, 4.0]))  # redundant copy of seq 2
    pub.send(Value(2, 4, old, 5.0))  # a minute old: expired
    pub.send(Value(2, 5, now, 6.0))
    got: list[float] = []
    while 6.0 not in got:
        packet = sub.recv()
        if isinstance(packet, Value):
            got.append(packet.value)
        elif isinstance(packet, Batch):
            got.extend(packet.values)
    assert got == [3.0, 4.0, 6.0]
    channel = pub.stats()["session"]["channels"]["2"]
    assert channel["overtaken"] == 2
    assert channel["duplicates"] == 1
    assert channel["expired"] == 1
    assert channel["values"] == 3
    assert channel["lost"] == 0
    assert channel["jitter_ns"] >= 0
    for key in ("rtt_ns", "one_way_ns", "overwritten"):
        assert key in channel


def test_values_are_stamped_when_the_middleware_delivers_them() -> None:
    """The stamp is taken on the adapter's callback thread, before the hop to the loop."""
    loop = asyncio.new_event_loop()
    try:
        handoff = LoopHandoff(loop)
        calls: list[tuple[list[float], int, int]] = []
        done = threading.Event()

        def on_loop(values: Sequence[Any], stamp_ns: int) -> None:
            calls.append((list(values), stamp_ns, time.time_ns()))
            done.set()
            loop.stop()

        callback = handoff.wrap(on_loop)
        before = time.time_ns()
        worker = threading.Thread(target=callback, args=([1.5],))
        worker.start()
        worker.join()
        after = time.time_ns()
        time.sleep(0.05)  # the loop is not running yet: the value waits in the hand-off
        loop.run_forever()
    finally:
        loop.close()
    assert done.is_set()
    [(values, stamp, ran_at)] = calls
    assert values == [1.5]
    assert before <= stamp <= after < ran_at


def test_outbound_puts_the_delivery_stamp_on_the_wire(
        server: ServerThread, raw_tcp: Callable[..., Any]) -> None:
    sub, pub = _pub_sub(raw_tcp, "/stamp")
    before = time.time_ns()
    pub.send(Value(2, 0, before, 1.0))
    packet = sub.expect(Value)
    assert packet.value == 1.0
    assert before <= packet.stamp_ns <= time.time_ns()
