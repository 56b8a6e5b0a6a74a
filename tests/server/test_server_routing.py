"""Values through a live server: mixed transports, many clients, batches, shutdown, Nagle."""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from rlbridge import ErrorCode
from rlbridge.csp.bridge import Bridge
from rlbridge.server import ServerError, ServerThread
from rlbridge.wire import Batch, Disconnect, Heartbeat, TopicAck, TopicConnect, Value
from rlbridge.wire.link import LinkState

F64 = "std_msgs/msg/Float64"
I64 = "std_msgs/msg/Int64"


def values_of(packet: Any) -> list[tuple[int, Any]]:
    """``(seq, value)`` pairs carried by a Value or Batch."""
    if isinstance(packet, Value):
        return [(packet.seq, packet.value)]
    assert isinstance(packet, Batch), packet
    return [(packet.first_seq + i, v) for i, v in enumerate(packet.values)]


def collect(client: Any, channel: int, n: int) -> list[tuple[int, Any]]:
    got: list[tuple[int, Any]] = []
    while len(got) < n:
        packet = client.recv()
        assert packet.channel == channel, packet
        got += values_of(packet)
    return got


def test_tcp_and_udp_channels_in_one_session(raw_tcp: Callable[..., Any],
                                             raw_udp: Callable[..., Any]) -> None:
    tcp = raw_tcp()
    ack = tcp.hello("mixed")
    udp = raw_udp()
    udp.token = ack.token  # the same session, reached over UDP
    udp.send(Heartbeat(1))  # tells the server this session's UDP address
    tcp.send(
        TopicConnect(1, "subscribe", "/mix/over_udp", F64, transport="udp"),
        TopicConnect(2, "subscribe", "/mix/over_tcp", F64, transport="tcp"),
        TopicConnect(3, "publish", "/mix/over_udp", F64, transport="tcp"),
        TopicConnect(4, "publish", "/mix/over_tcp", F64, transport="udp"),
    )
    assert sorted(tcp.expect(TopicAck).channel for _ in range(4)) == [1, 2, 3, 4]

    tcp.send(Value(3, 0, 0, 1.5))  # published over TCP, delivered over UDP
    token, packet = udp.recv_datagram()
    while isinstance(packet, Heartbeat):
        token, packet = udp.recv_datagram()
    assert token == ack.token
    assert isinstance(packet, Value)
    assert (packet.channel, packet.value) == (1, 1.5)

    udp.send(Value(4, 0, 0, 2.5))  # published over UDP, delivered over TCP
    packet = tcp.recv()
    assert isinstance(packet, Value)
    assert (packet.channel, packet.value) == (2, 2.5)

    session = tcp.stats()["session"]
    assert session["channels"]["3"]["values_in"] == 1
    assert session["channels"]["4"]["values_in"] == 1
    assert session["channels"]["1"]["values_out"] == 1
    assert session["channels"]["2"]["values_out"] == 1


def test_five_publishers_five_subscribers_in_order(bridge: Callable[..., Bridge]) -> None:
    n_clients, n_values = 5, 200
    subscribers = [bridge(name=f"sub{i}") for i in range(n_clients)]
    inboxes = [
        b.subscribe("/many", I64, transport="tcp", blocking=True, buffer_size=8192)
        for b in subscribers
    ]
    publishers = [bridge(name=f"pub{i}") for i in range(n_clients)]
    outs = [b.publish("/many", I64, transport="tcp") for b in publishers]

    def publish(k: int) -> None:
        for i in range(n_values):
            outs[k].write(k * 1_000_000 + i)

    threads = [threading.Thread(target=publish, args=(k,)) for k in range(n_clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    for inbox in inboxes:
        per_publisher: dict[int, list[int]] = {k: [] for k in range(n_clients)}
        for _ in range(n_clients * n_values):
            v = inbox.read(timeout=20)
            per_publisher[v // 1_000_000].append(v % 1_000_000)
        for k, seen in per_publisher.items():
            assert seen == list(range(n_values)), f"publisher {k} arrived out of order or lost"
        assert inbox.read_many() == []
        assert inbox.lost == 0


def test_batches_in_and_out(raw_tcp: Callable[..., Any]) -> None:
    sub = raw_tcp()
    sub.hello("sub")
    sub.send(TopicConnect(1, "subscribe", "/batch", I64, transport="tcp"))
    sub.expect(TopicAck)
    pub = raw_tcp()
    pub.hello("pub")
    pub.send(TopicConnect(9, "publish", "/batch", I64, transport="tcp"))
    pub.expect(TopicAck)

    pub.send(Batch(9, 0, [7] * 100, list(range(100))))
    got = collect(sub, 1, 100)
    assert got == [(i, i) for i in range(100)]
    # Overlapping batch (a resend): only the new half goes on.
    pub.send(Batch(9, 50, [7] * 100, list(range(50, 150))))
    got = collect(sub, 1, 50)
    assert [v for _, v in got] == list(range(100, 150))
    # Old values alone: nothing goes on; a value after a gap does, and the gap is counted.
    pub.send(Value(9, 20, 0, -1), Value(9, 160, 0, 160))
    assert collect(sub, 1, 1) == [(150, 160)]
    channel = pub.stats()["session"]["channels"]["9"]
    assert channel["values_in"] == 151
    assert channel["duplicates"] == 50
    assert channel["lost"] == 10


def test_empty_batch_moves_nothing(raw_tcp: Callable[..., Any]) -> None:
    sub = raw_tcp()
    sub.hello("sub")
    sub.send(TopicConnect(1, "subscribe", "/empty", I64, transport="tcp"))
    sub.expect(TopicAck)
    pub = raw_tcp()
    pub.hello("pub")
    pub.send(TopicConnect(2, "publish", "/empty", I64, transport="tcp"))
    pub.expect(TopicAck)
    pub.send(Batch(2, 1_000_000, [], []), Value(2, 0, 0, 5))
    assert collect(sub, 1, 1) == [(0, 5)]
    channel = pub.stats()["session"]["channels"]["2"]
    assert (channel["values_in"], channel["lost"]) == (1, 0)


def test_server_splits_batches_at_max_batch(make_server: Callable[..., ServerThread],
                                            raw_tcp: Callable[..., Any]) -> None:
    srv = make_server(max_batch=7)
    sub = raw_tcp(srv.port)
    assert sub.hello().limits.max_batch == 7
    sub.send(TopicConnect(1, "subscribe", "/split", I64, transport="tcp"))
    sub.expect(TopicAck)
    pub = raw_tcp(srv.port)
    pub.hello()
    pub.send(TopicConnect(1, "publish", "/split", I64, transport="tcp"))
    pub.expect(TopicAck)
    pub.send(Batch(1, 0, [0] * 30, list(range(30))))
    packets = []
    total = 0
    while total < 30:
        packet = sub.recv()
        packets.append(packet)
        total += len(values_of(packet))
    assert all(isinstance(p, Batch) and len(p.values) <= 7 for p in packets)
    assert [s for p in packets for s, _ in values_of(p)] == list(range(30))
    assert [v for p in packets for _, v in values_of(p)] == list(range(30))


def test_udp_batches_fit_the_datagram_budget(make_server: Callable[..., ServerThread],
                                             raw_tcp: Callable[..., Any],
                                             raw_udp: Callable[..., Any]) -> None:
    srv = make_server(udp_payload=512)
    sub = raw_udp(srv.port)
    sub.hello()
    sub.send(TopicConnect(1, "subscribe", "/big", "std_msgs/msg/String", transport="udp"))
    sub.expect(TopicAck)
    pub = raw_tcp(srv.port)
    pub.hello()
    pub.send(TopicConnect(1, "publish", "/big", "std_msgs/msg/String", transport="tcp"))
    pub.expect(TopicAck)
    values = [f"{i:03d}" + "x" * 100 for i in range(20)]
    pub.send(Batch(1, 0, [0] * 20, values))
    got: list[tuple[int, Any]] = []
    while len(got) < 20:
        sub.sock.settimeout(10)
        data = sub.sock.recv(1 << 16)
        _f, _t, packet = sub.codec.decode_datagram(data)
        if isinstance(packet, Heartbeat):
            continue
        assert len(data) <= 512
        got += values_of(packet)
    assert got == list(enumerate(values))


# -- shutdown ------------------------------------------------------------------------------


def test_shutdown_says_goodbye(make_server: Callable[..., ServerThread],
                               raw_tcp: Callable[..., Any], raw_udp: Callable[..., Any]) -> None:
    srv = make_server()
    port = srv.port
    tcp = raw_tcp(port)
    tcp.hello()
    udp = raw_udp(port)
    udp.hello()
    lost = threading.Event()
    with Bridge.connect("127.0.0.1", port, name="sdk", timeout=10) as sdk:
        sdk.on_link_change(lambda state: state is LinkState.LOST and lost.set())
        inbox = sdk.subscribe("/bye", F64, transport="tcp", blocking=True)
        assert sdk.link_state is LinkState.CONNECTED
        srv.stop()
        got = tcp.wait_closed()
        assert isinstance(got[-1], Disconnect), got
        assert got[-1].code == ErrorCode.SHUTTING_DOWN
        assert "shutting down" in got[-1].reason
        bye = udp.recv()
        assert isinstance(bye, Disconnect)
        assert bye.code == ErrorCode.SHUTTING_DOWN
        assert lost.wait(10), "the SDK did not notice the shutdown"
        assert sdk.link_state is LinkState.LOST
        with pytest.raises(TimeoutError):
            inbox.read(timeout=0.01)
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", port), timeout=5).close()


# -- TCP_NODELAY, checked on the real sockets ----------------------------------------------


def _tcp_inodes() -> dict[int, tuple[int, int]]:
    """inode -> (local port, remote port) of this host's IPv4 TCP sockets."""
    table: dict[int, tuple[int, int]] = {}
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        local, remote, inode = fields[1], fields[2], int(fields[9])
        table[inode] = (int(local.split(":")[1], 16), int(remote.split(":")[1], 16))
    return table


def nodelay_of_connections(server_port: int) -> dict[str, list[int]]:
    """TCP_NODELAY of this process's connected sockets to/from ``server_port``, by side."""
    inodes = _tcp_inodes()
    sides: dict[str, list[int]] = {"server": [], "client": []}
    for fd_name in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd_name}")
        except FileNotFoundError:
            continue
        if not target.startswith("socket:["):
            continue
        ports = inodes.get(int(target[8:-1]))
        if ports is None:
            continue
        local, remote = ports
        if local == server_port and remote != 0:
            side = "server"
        elif remote == server_port:
            side = "client"
        else:
            continue
        with socket.socket(fileno=os.dup(int(fd_name))) as sock:
            sides[side].append(sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))
    return sides


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize(
    ("server_nodelay", "client_nodelay", "use_uvloop"),
    [(False, False, True), (True, False, True), (False, True, True), (True, True, True),
     (False, False, False), (True, False, False)],
)
def test_nodelay(make_server: Callable[..., ServerThread], server_nodelay: bool,
                 client_nodelay: bool, use_uvloop: bool) -> None:
    """Nagle stays on unless asked (event loops turn it off by default), and off when asked."""
    srv = make_server(nodelay=server_nodelay, use_uvloop=use_uvloop)
    with Bridge.connect("127.0.0.1", srv.port, nodelay=client_nodelay, timeout=10) as b:
        b.server_stats()  # the server has accepted and configured the connection
        sides = nodelay_of_connections(srv.port)
    assert len(sides["server"]) == 1, sides
    assert len(sides["client"]) == 1, sides
    assert bool(sides["server"][0]) is server_nodelay
    assert bool(sides["client"][0]) is client_nodelay


def test_port_in_use_is_a_server_error() -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        srv = ServerThread(port=port)
        with pytest.raises(ServerError, match=f"cannot listen on 127.0.0.1 TCP port {port}: "
                           "address already in use"):
            srv.start()
        srv.stop()
