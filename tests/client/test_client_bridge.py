"""The client SDK against a live server: lifetime, channels, buffering, refusals, failures."""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable
from typing import Any

import pytest

from rlbridge import ConnectionClosed, ConnectionFailed, ErrorCode, Policy, RemoteError, Tuning
from rlbridge.csp.bridge import Bridge
from rlbridge.errors import (
    BindingRefused,
    ChannelClosed,
    NoSuchFieldError,
    NoValueYet,
    TypeClashError,
    UnknownTypeError,
)
from rlbridge.server import ServerThread
from rlbridge.wire.link import LinkState

F64 = "std_msgs/msg/Float64"
TWIST = "geometry_msgs/msg/Twist"
ZERO3 = {"x": 0.0, "y": 0.0, "z": 0.0}


def sdk_threads() -> list[threading.Thread]:
    """Live threads the SDK starts (the test server's own thread is not one of them)."""
    return [t for t in threading.enumerate()
            if t.name.startswith("rlbridge-") and t.name != "rlbridge-server"]


# -- lifetime ------------------------------------------------------------------------------


def test_connect_close_idempotent_and_threads_joined(server: ServerThread) -> None:
    assert sdk_threads() == []
    b = Bridge.connect("127.0.0.1", server.port, name="lifetime", timeout=10)
    names = {t.name for t in sdk_threads()}
    assert {"rlbridge-recv", "rlbridge-send"} <= names
    assert b.link_state is LinkState.CONNECTED
    assert b.session_id >= 1
    inbox = b.subscribe("/life", F64, transport="tcp", blocking=True)
    out = b.publish("/life", F64, transport="tcp")
    b.close()
    assert sdk_threads() == [], "close() left SDK threads running"
    assert b.link_state is LinkState.LOST
    b.close()  # idempotent
    assert inbox.closed
    with pytest.raises(ChannelClosed):
        out.write(1.0)
    with pytest.raises(ConnectionClosed, match="bridge is closed"):
        b.send()


def test_context_manager_closes(server: ServerThread, raw_tcp: Callable[..., Any],
                                wait_until: Callable[..., Any]) -> None:
    watcher = raw_tcp()
    watcher.hello()
    with Bridge.connect("127.0.0.1", server.port, name="ctx", timeout=10) as b:
        b.subscribe("/ctx/topic", F64, transport="tcp")
        assert ["/ctx/topic", F64] in watcher.stats()["topics"]
    assert sdk_threads() == []
    # The goodbye reached the server: the session and its subscription are gone.
    wait_until(lambda: ["/ctx/topic", F64] not in watcher.stats()["topics"],
               what="the server to drop the closed session's topic")


def test_close_after_an_exception_in_the_with_block(server: ServerThread) -> None:
    with pytest.raises(RuntimeError, match="boom"), Bridge.connect(
            "127.0.0.1", server.port, timeout=10):
        raise RuntimeError("boom")
    assert sdk_threads() == []


def test_server_stats_and_rtt(bridge: Callable[..., Bridge],
                              wait_until: Callable[..., Any]) -> None:
    b = bridge(name="stats-user")
    stats = b.server_stats()
    assert stats["session"]["name"] == "stats-user"
    assert stats["session"]["session"] == b.session_id
    assert stats["server"]["sessions_opened"] >= 1
    wait_until(lambda: b.rtt_ns > 0, what="an RTT sample from heartbeats")


# -- subscribing ---------------------------------------------------------------------------


def test_non_blocking_subscribe_returns_the_latest(bridge: Callable[..., Bridge],
                                                  wait_until: Callable[..., Any]) -> None:
    sub, pub = bridge(), bridge()
    latest = sub.subscribe("/latest", F64, transport="tcp")
    with pytest.raises(NoValueYet):
        latest.read()
    out = pub.publish("/latest", F64, transport="tcp")
    for v in (1.0, 2.0, 3.0):
        out.write(v)
    def latest_is_3() -> bool:
        try:
            return latest.read() == 3.0
        except NoValueYet:
            return False

    wait_until(latest_is_3, what="the latest value")
    assert latest.read() == 3.0  # nothing new: the latest again
    assert latest.read() == 3.0
    assert latest.statistics().stale_reads >= 2


def test_non_blocking_subscribe_with_initial(bridge: Callable[..., Bridge],
                                             wait_until: Callable[..., Any]) -> None:
    sub, pub = bridge(), bridge()
    ch = sub.subscribe("/initial", F64, transport="tcp", initial=-1.0)
    assert ch.read() == -1.0
    pub.publish("/initial", F64, transport="tcp").write(8.0)
    wait_until(lambda: ch.read() == 8.0, what="the published value")


def test_blocking_read_times_out(bridge: Callable[..., Bridge]) -> None:
    ch = bridge().subscribe("/silent", F64, transport="tcp", blocking=True)
    with pytest.raises(TimeoutError):
        ch.read(timeout=0.05)


def test_blocking_read_gets_every_value_in_order(bridge: Callable[..., Bridge]) -> None:
    sub, pub = bridge(), bridge()
    ch = sub.subscribe("/every", "std_msgs/msg/Int32", transport="tcp", blocking=True,
                       buffer_size=1000)
    out = pub.publish("/every", "std_msgs/msg/Int32", transport="tcp")
    for i in range(500):
        out.write(i)
    assert [ch.read(timeout=10) for _ in range(500)] == list(range(500))
    assert ch.lost == 0


def test_buffer_size_zero_is_refused(bridge: Callable[..., Bridge]) -> None:
    b = bridge()
    with pytest.raises(ValueError, match="buffer_size >= 1"):
        b.subscribe("/zero", F64, buffer_size=0)
    # and nothing was bound on the server
    assert ["/zero", F64] not in [list(t) for t in b.server_stats()["topics"]]


def test_unsubscribe(bridge: Callable[..., Bridge], wait_until: Callable[..., Any]) -> None:
    b = bridge()
    ch = b.subscribe("/unsub", F64, transport="tcp")
    assert ["/unsub", F64] in b.server_stats()["topics"]
    b.unsubscribe(ch)
    assert ch.closed
    wait_until(lambda: ["/unsub", F64] not in b.server_stats()["topics"],
               what="the server to drop the topic")


# -- publishing ----------------------------------------------------------------------------


def test_through_buffer_values_wait_for_send(bridge: Callable[..., Bridge]) -> None:
    pub, sub = bridge(name="pub"), bridge(name="sub")
    data_in = sub.subscribe("/tb/data", F64, transport="tcp", blocking=True, buffer_size=64)
    marker_in = sub.subscribe("/tb/marker", F64, transport="tcp", blocking=True)
    data_out = pub.publish("/tb/data", F64, transport="tcp", through_buffer=True)
    marker_out = pub.publish("/tb/marker", F64, transport="tcp")  # immediate
    for v in (1.0, 2.0, 3.0):
        data_out.write(v)
    assert data_out.pending() == 3
    # The marker goes out at once on the same connection, after the buffered writes: had those
    # been sent, they would have reached the subscriber before it.
    marker_out.write(9.0)
    assert marker_in.read(timeout=10) == 9.0
    assert data_in.read_many() == []
    assert data_out.pending() == 3
    pub.send(wait=True)
    assert data_out.pending() == 0
    assert [data_in.read(timeout=10) for _ in range(3)] == [1.0, 2.0, 3.0]


def test_send_rate_hz_sends_without_send(server: ServerThread,
                                         bridge: Callable[..., Bridge]) -> None:
    sub = bridge()
    inbox = sub.subscribe("/rate", F64, transport="tcp", blocking=True, buffer_size=64)
    pub = bridge(send_rate_hz=50.0)
    out = pub.publish("/rate", F64, transport="tcp", through_buffer=True)
    for v in (1.0, 2.0, 3.0, 4.0):
        out.write(v)
    assert [inbox.read(timeout=10) for _ in range(4)] == [1.0, 2.0, 3.0, 4.0]


def test_invalid_send_rate(server: ServerThread) -> None:
    with pytest.raises(ValueError, match=r"send_rate_hz=-1\.0 must be positive"):
        Bridge.connect("127.0.0.1", server.port, send_rate_hz=-1.0, timeout=10)
    assert sdk_threads() == [], "a refused connect left its receive thread running"


def test_full_outgoing_buffer_overwrites_and_counts(bridge: Callable[..., Bridge]) -> None:
    pub, sub = bridge(), bridge()
    inbox = sub.subscribe("/full", F64, transport="tcp", blocking=True, buffer_size=16)
    out = pub.publish("/full", F64, transport="tcp", through_buffer=True, buffer_size=4)
    for v in range(10):
        out.write(float(v))
    assert out.statistics().overwritten == 6
    pub.send(wait=True)
    assert [inbox.read(timeout=10) for _ in range(4)] == [6.0, 7.0, 8.0, 9.0]


@pytest.mark.parametrize("transport", ["tcp", "udp"])
def test_whole_messages_and_nested_fields(bridge: Callable[..., Bridge], transport: Any) -> None:
    pub, sub = bridge(), bridge()
    whole = sub.subscribe("/twist", TWIST, None, transport=transport, blocking=True,
                          buffer_size=16)
    linear_x = sub.subscribe("/twist", TWIST, "linear.x", transport=transport, blocking=True,
                             buffer_size=16)
    angular_z = sub.subscribe("/twist", TWIST, "angular.z", transport=transport,
                              blocking=True, buffer_size=16)
    assert whole.msg_type == TWIST
    out_msg = pub.publish("/twist", TWIST, None, transport=transport)
    out_x = pub.publish("/twist", TWIST, "linear.x", transport=transport)

    msg = {"linear": {"x": 1.0, "y": 2.0, "z": 3.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.5}}
    out_msg.write(msg)
    assert whole.read(timeout=10) == msg
    assert linear_x.read(timeout=10) == 1.0
    assert angular_z.read(timeout=10) == 0.5

    out_msg.write({"linear": {"x": 4.0}})  # missing fields take the type's defaults
    assert whole.read(timeout=10) == {"linear": {**ZERO3, "x": 4.0}, "angular": ZERO3}
    assert linear_x.read(timeout=10) == 4.0
    assert angular_z.read(timeout=10) == 0.0

    out_x.write(7.0)  # one field published: a fresh message around it
    assert whole.read(timeout=10) == {"linear": {**ZERO3, "x": 7.0}, "angular": ZERO3}
    assert linear_x.read(timeout=10) == 7.0
    assert angular_z.read(timeout=10) == 0.0


def test_udp_redundancy_delivers_each_value_once(bridge: Callable[..., Bridge]) -> None:
    """The server repeats the last k values in every datagram; the SDK drops the repeats."""
    pub, sub = bridge(), bridge()
    inbox = sub.subscribe("/redundant", "std_msgs/msg/Int32", transport="udp", blocking=True,
                          buffer_size=256, policy=Policy(redundancy=3))
    out = pub.publish("/redundant", "std_msgs/msg/Int32", transport="tcp")
    for i in range(10):  # one at a time, so that each goes out in its own datagram
        out.write(i)
        assert inbox.read(timeout=10) == i
    assert inbox.read_many() == []
    # Datagrams 2, 3 and 4..10 repeated 1, 2 and 3 earlier values: recognised and dropped.
    assert inbox.duplicates == 1 + 2 + 3 * 7
    assert inbox.lost == 0


# -- refusals carry the server's reason ----------------------------------------------------


def test_unknown_type(bridge: Callable[..., Bridge]) -> None:
    b = bridge()
    with pytest.raises(UnknownTypeError) as exc:
        b.subscribe("/t", "std_msgs/msg/Float65")
    assert exc.value.code is ErrorCode.UNKNOWN_TYPE
    assert "unknown message type 'std_msgs/msg/Float65'" in exc.value.reason
    assert "[UNKNOWN_TYPE]" in str(exc.value)
    assert isinstance(exc.value, BindingRefused)
    with pytest.raises(UnknownTypeError, match="not a message type name"):
        b.publish("/t", "Float64")
    assert b.subscribe("/t", F64, transport="tcp") is not None  # still usable


def test_no_such_field(bridge: Callable[..., Bridge]) -> None:
    b = bridge()
    with pytest.raises(NoSuchFieldError) as exc:
        b.publish("/f", TWIST, "linear.q")
    assert exc.value.code is ErrorCode.NO_SUCH_FIELD
    assert "has no field 'linear.q'" in exc.value.reason
    assert "x, y, z" in exc.value.reason


def test_type_clash(bridge: Callable[..., Bridge]) -> None:
    a, b = bridge(), bridge()
    a.publish("/clash", F64, transport="tcp")
    with pytest.raises(TypeClashError) as exc:
        b.subscribe("/clash", "std_msgs/msg/String")
    assert exc.value.code is ErrorCode.TYPE_CLASH
    assert exc.value.reason == ("topic '/clash' has type std_msgs/msg/Float64, "
                                "not std_msgs/msg/String")
    assert b.subscribe("/clash", F64, transport="tcp") is not None


def test_bad_topic_name(bridge: Callable[..., Bridge]) -> None:
    with pytest.raises(BindingRefused) as exc:
        bridge().subscribe("not/absolute", F64)
    assert exc.value.code is ErrorCode.BAD_TOPIC
    assert isinstance(exc.value, RemoteError)
    assert "'not/absolute' is not a valid topic name" in exc.value.reason


# -- UDP control and connection failures ---------------------------------------------------


def test_udp_only_session_with_sdk(make_server: Callable[..., ServerThread]) -> None:
    srv = make_server(tcp=False)
    with Bridge.connect("127.0.0.1", srv.port, tuning=Tuning(control="udp"), timeout=10) as pub, \
            Bridge.connect("127.0.0.1", srv.port, tuning=Tuning(control="udp"), timeout=10) as sub:
        inbox = sub.subscribe("/u", F64, transport="udp", blocking=True, buffer_size=64)
        out = pub.publish("/u", F64, transport="udp")
        out.write(3.5)
        assert inbox.read(timeout=10) == 3.5
        with pytest.raises(BindingRefused, match="without a TCP connection"):
            sub.subscribe("/u", F64, transport="tcp")
    with pytest.raises(ConnectionFailed, match="cannot reach"):
        Bridge.connect("127.0.0.1", srv.port, timeout=10)  # no TCP listener


@pytest.mark.timeout(20)  # refusal must not wait out the 60 s connect timeout
@pytest.mark.parametrize("control", ["tcp", "udp"])
def test_connect_where_nothing_listens(free_port: Callable[[], int], control: Any) -> None:
    port = free_port()
    with pytest.raises(ConnectionFailed) as exc:
        Bridge.connect("127.0.0.1", port, tuning=Tuning(control=control), timeout=60)
    message = str(exc.value)
    assert f"127.0.0.1:{port}" in message
    assert "cannot reach rlbridge server" in message
    assert "refused" in message.lower()
    assert sdk_threads() == []


def test_connect_to_a_server_that_never_answers() -> None:
    with socket.socket() as mute:
        mute.bind(("127.0.0.1", 0))
        mute.listen()
        port = mute.getsockname()[1]
        with pytest.raises(ConnectionFailed, match=r"no answer from 127\.0\.0\.1:\d+ within"):
            Bridge.connect("127.0.0.1", port, timeout=0.3)
    assert sdk_threads() == []


def test_connect_to_a_server_that_hangs_up() -> None:
    with socket.socket() as rude:
        rude.bind(("127.0.0.1", 0))
        rude.listen()
        port = rude.getsockname()[1]

        def hang_up() -> None:
            conn, _ = rude.accept()
            conn.recv(100)
            conn.close()

        t = threading.Thread(target=hang_up)
        t.start()
        with pytest.raises(ConnectionFailed, match="closed the connection"):
            Bridge.connect("127.0.0.1", port, timeout=10)
        t.join(10)
