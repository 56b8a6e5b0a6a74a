"""Per-session and per-channel counters after a known traffic pattern, over TCP and UDP.

Each test sends an exact pattern (good values, late and duplicate sequence numbers, values of
the wrong kind, undecodable packets, values on unknown channels) and checks every counter the
``Stats`` reply carries for it, then the server totals, which must also keep what closed
sessions counted.
"""

from __future__ import annotations

import socket
from collections.abc import Callable
from typing import Any

from rlbridge.wire import (
    Batch,
    Error,
    FrameDecoder,
    Hello,
    PacketCodec,
    Stats,
    TopicAck,
    TopicConnect,
    TopicError,
    Value,
)
from rlbridge.wire.codec import DATAGRAM_HEADER, FRAME_HEADER, MAGIC, PROTOCOL_VERSION
from waiting import wait_until

F64 = "std_msgs/msg/Float64"
#: Value(channel 1, seq="x", ...): decodes far enough to name channel 1, then fails.
BROKEN_VALUE_CH1 = b"\x95\x08\x01\xa1x\x00\x01"


def frame(body: bytes) -> bytes:
    return FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, len(body)) + body


def send_pattern(client: Any, transport: str, send_raw: Callable[[bytes], None]) -> None:
    """Channel 1 publishes; the pattern's expected counters are in ``check_pattern``."""
    client.send(TopicConnect(1, "publish", f"/stats/{transport}", F64, transport=transport))
    assert client.expect(TopicAck).channel == 1
    for seq in range(5):
        client.send(Value(1, seq, 0, float(seq)))           # 5 values in
    client.send(Value(1, 2, 0, 2.0))                         # late (overtaken)
    client.send(Value(1, 4, 0, 4.0))                         # late (duplicate)
    client.send(Batch(1, 5, [0, 0, 0], [5.0, 6.0, 7.0]))     # 3 more in
    client.send(Value(1, 8, 0, "eight"))                     # wrong kind: bad value
    assert client.expect(Error).channel == 1
    send_raw(BROKEN_VALUE_CH1)                               # malformed, names channel 1
    assert client.expect(Error).channel == 1
    client.send(Batch(9, 0, [0, 0], [1.0, 2.0]))             # unknown channel: 2 dropped
    assert client.expect(Error).channel == 9


def check_pattern(session: dict[str, Any]) -> None:
    ch = session["channels"]["1"]
    assert ch["direction"] == "publish"
    assert ch["values_in"] == 8
    assert ch["late"] == 2
    assert ch["bad_values"] == 1
    assert ch["malformed"] == 1
    assert session["values_in"] == 8
    assert session["late"] == 2
    assert session["dropped"] == 2
    assert session["malformed"] == 1
    assert session["bad_values"] == 1
    assert session["errors_sent"] == 3
    assert session["bytes_in"] > 0
    assert session["bytes_out"] > 0


def test_counters_over_tcp(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.hello("stats-tcp")
    send_pattern(client, "tcp", lambda body: client.send_bytes(frame(body)))
    body = client.stats()
    check_pattern(body["session"])
    mine = [s for s in body["sessions"] if s["session"] == body["session"]["session"]]
    assert len(mine) == 1
    assert mine[0]["channels"]["1"]["values_in"] == 8
    assert body["server"]["values_in"] >= 8
    assert body["server"]["malformed"] >= 1


def test_counters_over_udp(raw_udp: Callable[..., Any]) -> None:
    client = raw_udp()
    ack = client.hello("stats-udp")
    header = DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, ack.token)
    send_pattern(client, "udp", lambda body: client.send_bytes(header + body))
    client.send(Stats())
    body = client.expect(Stats).body
    check_pattern(body["session"])
    # A datagram cannot carry every session's counters: a UDP control path gets its own.
    assert "sessions" not in body
    assert body["server"]["values_in"] >= 8


def test_totals_keep_closed_channels_and_sessions(raw_tcp: Callable[..., Any],
                                                  wait_until: Callable[..., Any]) -> None:
    watcher = raw_tcp()
    watcher.hello("watcher")
    before = watcher.stats()["server"]
    client = raw_tcp()
    client.hello("leaves")
    client.send(TopicConnect(1, "publish", "/stats/closed", F64, transport="tcp"))
    client.expect(TopicAck)
    client.send(Batch(1, 0, [0] * 10, [1.0] * 10))
    wait_until(lambda: watcher.stats()["server"]["values_in"] == before["values_in"] + 10,
               what="the values to be counted")
    client.close()
    wait_until(lambda: watcher.stats()["server"]["sessions"] == before["sessions"],
               what="the session to close")
    after = watcher.stats()["server"]
    assert after["values_in"] == before["values_in"] + 10
    assert after["sessions_opened"] == before["sessions_opened"] + 1


def test_subscriber_counts_values_out(raw_tcp: Callable[..., Any],
                                      wait_until: Callable[..., Any]) -> None:
    sub = raw_tcp()
    sub.hello("sub")
    sub.send(TopicConnect(3, "subscribe", "/stats/out", F64, transport="tcp"))
    sub.expect(TopicAck)
    pub = raw_tcp()
    pub.hello("pub")
    pub.send(TopicConnect(1, "publish", "/stats/out", F64, transport="tcp"))
    pub.expect(TopicAck)
    pub.send(Batch(1, 0, [0] * 7, [float(i) for i in range(7)]))
    got: list[float] = []
    while len(got) < 7:
        packet = sub.recv()
        if isinstance(packet, Value | Batch):
            got += [packet.value] if isinstance(packet, Value) else packet.values
    ch = sub.stats()["session"]["channels"]["3"]
    assert (ch["direction"], ch["values_out"], ch["dropped"]) == ("subscribe", 7, 0)


def test_slow_consumer_is_bounded_and_counted(make_server: Callable[..., Any]) -> None:
    """A subscriber that never reads: its queue stays at the bound, drops are counted, and a
    subscriber that reads on the same topic gets every value."""
    limit = 64 << 10
    srv = make_server(max_write_buffer=limit, timeout_ms=60_000, heartbeat_ms=1000)
    codec = PacketCodec()

    def connect(name: str, rcvbuf: int | None = None) -> socket.socket:
        sock = socket.socket()
        if rcvbuf is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        sock.connect(("127.0.0.1", srv.port))
        sock.settimeout(30)
        sock.sendall(codec.encode_frame(Hello(PROTOCOL_VERSION, name)))
        return sock

    def read_until(sock: socket.socket, pred: Callable[[Any], bool]) -> list[Any]:
        decoder = decoders.setdefault(sock.fileno(), FrameDecoder(codec))
        seen: list[Any] = []

        def arrived() -> bool:
            for packet in decoder.feed(sock.recv(1 << 16)):
                seen.append(packet)
                if pred(packet):
                    return True
            return False

        wait_until(arrived, lambda: f"the expected packet (came: {seen[-5:]})", timeout=30,
                   interval=0)
        return seen

    decoders: dict[int, FrameDecoder] = {}
    slow = connect("slow", rcvbuf=4096)
    slow.sendall(codec.encode_frame(TopicConnect(1, "subscribe", "/slow", F64, transport="tcp")))
    read_until(slow, lambda p: isinstance(p, TopicAck | TopicError))
    fast = connect("fast")
    fast_dec = FrameDecoder(codec)
    fast.sendall(codec.encode_frame(TopicConnect(1, "subscribe", "/slow", F64, transport="tcp")))
    pub = connect("pub")
    pub.sendall(codec.encode_frame(TopicConnect(1, "publish", "/slow", F64, transport="tcp")))
    read_until(pub, lambda p: isinstance(p, TopicAck))
    total, chunk = 800_000, 4000  # ~8 MB: more than the kernel buffers hold
    received = 0
    try:
        for first in range(0, total, chunk):  # the slow one never reads again
            pub.sendall(codec.encode_frame(Batch(1, first, [0] * chunk, [1.0] * chunk)))
            while received < first + chunk:  # lockstep: the reader keeps up
                received += _values(fast_dec.feed(fast.recv(1 << 20)))
        assert received == total, "the reading subscriber must get every value"
        pub.sendall(codec.encode_frame(Stats()))
        body = read_until(pub, lambda p: isinstance(p, Stats))[-1].body
        by_name = {s["name"]: s for s in body["sessions"]}
        slow_stats = by_name["slow"]
        ch = slow_stats["channels"]["1"]
        assert ch["values_out"] == total
        assert ch["dropped"] > 0, "a stalled reader's values must be dropped, and counted"
        assert slow_stats["dropped"] == ch["dropped"]
        # The queue never grows past the bound plus the one batch that crossed it.
        assert slow_stats["tcp_queued_bytes"] <= limit + (64 << 10)
        assert by_name["fast"]["dropped"] == 0
        assert body["server"]["dropped"] >= ch["dropped"]
    finally:
        for sock in (slow, fast, pub):
            sock.close()


def _values(packets: list[Any]) -> int:
    return sum(len(p.values) if isinstance(p, Batch) else 1
               for p in packets if isinstance(p, Value | Batch))
