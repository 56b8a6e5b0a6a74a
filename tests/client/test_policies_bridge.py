"""Channel policies end to end through the SDK: a live server, and a stalled fake server."""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from rlbridge import Policy, Tuning
from rlbridge.client.bridge import Bridge
from rlbridge.client.channels.health import ChannelHealth
from rlbridge.wire import (
    Batch,
    ConnectAck,
    FrameDecoder,
    Hello,
    Limits,
    PacketCodec,
    TopicAck,
    TopicConnect,
    Value,
)
from waiting import wait_until

F64 = "std_msgs/msg/Float64"
STR = "std_msgs/msg/String"
WAIT = 10.0


def test_udp_redundancy_from_the_sdk_is_deduplicated_by_the_server(
        bridge: Callable[..., Bridge]) -> None:
    b = bridge()
    sub = b.subscribe("/red/up", F64, transport="tcp", blocking=True, buffer_size=64)
    out = b.publish("/red/up", F64, transport="udp", policy=Policy(redundancy=2))
    for i in range(20):
        out.write(float(i))
        b.send(wait=True)  # one datagram per value, each repeating up to 2 earlier ones
    got = [sub.read(timeout=WAIT) for _ in range(20)]
    assert got == [float(i) for i in range(20)]
    channel = wait_until(lambda: (c := b.server_stats()["session"]["channels"][str(out.channel_id)])
                    ["values"] == 20 and c, "server counters")
    assert channel["duplicates"] == 2 * 20 - 3  # 0 + 1 + 2 * 18 copies dropped
    assert channel["lost"] == 0
    assert channel["values"] == 20


def test_health_on_both_channel_kinds(bridge: Callable[..., Bridge]) -> None:
    b = bridge()
    sub = b.subscribe("/health", F64, transport="udp", blocking=True, buffer_size=16,
                      policy=Policy(latest=False, max_age_ms=5_000))
    out = b.publish("/health", F64, transport="tcp")
    for i in range(5):
        out.write(float(i))
    assert [sub.read(timeout=WAIT) for _ in range(5)] == [0.0, 1.0, 2.0, 3.0, 4.0]
    wait_until(lambda: b.rtt_ns > 0, "an RTT sample")
    h = sub.health()
    assert isinstance(h, ChannelHealth)
    assert (h.values, h.lost, h.expired) == (5, 0, 0)
    assert h.rtt_ns > 0
    assert 0 <= h.one_way_ns < 5_000_000_000
    assert h.jitter_ns >= 0
    assert h.clock_error_ns >= 0  # same host: the offset estimate exists and is bounded
    oh = out.health()
    assert oh.values == 5
    assert oh.rtt_ns > 0
    assert oh.one_way_ns == oh.rtt_ns // 2
    out.write(9.0)
    value, age = sub.read_with_age(timeout=WAIT)
    assert value == 9.0
    # Corrected by the clock-offset estimate, whose error on a loaded machine (asymmetric
    # delays) can exceed a fresh value's true age: the sign is not the mechanism here.
    assert abs(age) < 5_000_000_000


def test_max_age_drops_on_the_sdk_side(bridge: Callable[..., Bridge]) -> None:
    """Values arrive through the server stamped at middleware delivery; a 1 ns limit drops
    every one of them (always older on arrival), which the SDK counts."""
    b = bridge()
    sub = b.subscribe("/age", F64, transport="tcp", initial=-1.0, policy=Policy(max_age_ms=0))
    strict = b.subscribe("/age", F64, transport="tcp", initial=-1.0, policy=Policy(max_age_ms=1))
    out = b.publish("/age", F64, transport="tcp")
    out.write(1.0)
    wait_until(lambda: sub.read() == 1.0, "the value on the unlimited channel")
    # Whether it expired depends on the machine's speed; it is counted either way.
    wait_until(lambda: strict.health().expired + strict.health().values == 1, "the strict channel")
    assert strict.health().expired == 1 or strict.read() == 1.0


# -- client -> server latest, against a fake server that stops reading ---------------------


class StallingServer:
    """Accepts one SDK, answers its hello and topic-connects, then reads only when told."""

    def __init__(self) -> None:
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        # A small window, set before the connection exists (accepted sockets inherit it);
        # shrinking it later makes the kernel prune segments and back off for seconds.
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(1)
        self.port: int = self.listener.getsockname()[1]
        self.codec = PacketCodec()
        self.decoder = FrameDecoder(self.codec)
        self.conn: socket.socket | None = None
        self.values: list[tuple[int, Any]] = []
        self.stalled = threading.Event()
        self._thread = threading.Thread(target=self._handshake, daemon=True)
        self._thread.start()

    def _send(self, packet: Any) -> None:
        assert self.conn is not None
        self.conn.sendall(self.codec.encode_frame(packet))

    def _handshake(self) -> None:
        self.listener.settimeout(WAIT)
        conn, _ = self.listener.accept()
        self.conn = conn
        conn.settimeout(WAIT)
        while True:
            for packet in self.decoder.feed(conn.recv(4096)):
                if isinstance(packet, Hello):
                    self._send(ConnectAck(1, 77, 100, 60_000, Limits(1 << 16, 16, 8)))
                elif isinstance(packet, TopicConnect):
                    self._send(TopicAck(packet.channel, packet.msg_type, ""))
                    self.stalled.set()
                    return

    def drain_until(self, last: Any) -> None:
        assert self.conn is not None
        conn = self.conn

        def arrived() -> bool:
            if self.values and self.values[-1][1] == last:
                return True
            for packet in self.decoder.feed(conn.recv(1 << 16)):
                if isinstance(packet, Value):
                    self.values.append((packet.seq, packet.value))
                elif isinstance(packet, Batch):
                    self.values.extend(
                        (packet.first_seq + i, v) for i, v in enumerate(packet.values))
            return False

        wait_until(arrived, lambda: f"{last[:8]!r} ({len(self.values)} values came)",
                   timeout=WAIT, interval=0)

    def close(self) -> None:
        self._thread.join(WAIT)
        if self.conn is not None:
            self.conn.close()
        self.listener.close()


@pytest.fixture
def stalling_server() -> Iterator[StallingServer]:
    srv = StallingServer()
    yield srv
    srv.close()


@pytest.mark.parametrize("latest", [True, False])
def test_sdk_latest_channel_holds_while_the_server_stalls(
        stalling_server: StallingServer, latest: bool) -> None:
    b = Bridge.connect("127.0.0.1", stalling_server.port, tuning=Tuning(control="tcp"),
                       timeout=WAIT)
    try:
        out = b.publish("/stall", STR, transport="tcp", policy=Policy(latest=latest),
                        buffer_size=4096)
        assert stalling_server.stalled.wait(WAIT)
        sent = [f"{i:04d}" + "y" * 2000 for i in range(300)]
        for value in sent:
            out.write(value)
        if latest:  # the send thread saw the kernel queue back up and held values back
            wait_until(lambda: out.health().overtaken > 0, "overtaken values")
        stalling_server.drain_until(sent[-1])
        h = out.health()
    finally:
        b.close()
    got = [v for _, v in stalling_server.values]
    seqs = [s for s, _ in stalling_server.values]
    assert got[-1] == sent[-1]
    assert seqs == list(range(len(seqs)))
    if latest:
        assert len(got) < len(sent)
        assert h.overtaken == len(sent) - len(got)
    else:
        assert got == sent
        assert h.overtaken == 0
