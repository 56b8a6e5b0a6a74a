"""TCP sessions on a live server: handshake, refusals, garbage, malformed packets."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from rlbridge import ErrorCode
from rlbridge.server import ServerThread
from rlbridge.wire import (
    FRAME_HEADER,
    MAGIC,
    PROTOCOL_VERSION,
    ConnectAck,
    ConnectError,
    Disconnect,
    Error,
    Heartbeat,
    Hello,
    Malformed,
    PacketCodec,
    Stats,
    TopicAck,
    TopicConnect,
    TopicError,
    Value,
)

F64 = "std_msgs/msg/Float64"


def test_hello_gets_an_ack(server: ServerThread, raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    ack = client.hello("tester")
    assert isinstance(ack, ConnectAck)
    assert ack.session >= 1
    assert ack.token != 0
    assert ack.heartbeat_ms == server.server.config.heartbeat_ms
    assert ack.timeout_ms == server.server.config.timeout_ms
    assert ack.limits.max_packet == server.server.config.max_packet
    assert ack.limits.max_channels == server.server.config.max_channels
    assert ack.limits.max_batch == server.server.config.max_batch
    body = client.stats()
    assert body["session"]["session"] == ack.session
    assert body["session"]["name"] == "tester"
    assert body["server"]["sessions_opened"] == 1


def test_sessions_get_distinct_ids_and_tokens(raw_tcp: Callable[..., Any]) -> None:
    acks = [raw_tcp().hello(f"c{i}") for i in range(4)]
    assert len({a.session for a in acks}) == 4
    assert len({a.token for a in acks}) == 4


def test_server_sends_heartbeats(make_server: Callable[..., ServerThread],
                                 raw_tcp: Callable[..., Any]) -> None:
    srv = make_server(heartbeat_ms=20, timeout_ms=5000)
    client = raw_tcp(srv.port)
    client.hello()
    beats = [client.recv(skip=()) for _ in range(3)]
    assert all(isinstance(b, Heartbeat) for b in beats), beats
    assert beats[0].sent_ns < beats[1].sent_ns < beats[2].sent_ns


def test_heartbeat_echo_gives_the_server_an_rtt(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.hello()
    beat = client.recv(skip=())
    assert isinstance(beat, Heartbeat)
    client.send(Heartbeat(sent_ns=1, echo_ns=beat.sent_ns))
    rtt = client.stats()["session"]["rtt_us"]
    assert rtt is not None
    assert rtt >= 0


@pytest.mark.parametrize(
    ("first", "code", "phrase"),
    [
        (Hello(PROTOCOL_VERSION + 1, "future"), ErrorCode.UNSUPPORTED_VERSION,
         f"client speaks protocol {PROTOCOL_VERSION + 1}, server speaks {PROTOCOL_VERSION}"),
        (Value(1, 0, 0, 1.0), ErrorCode.UNEXPECTED, "expected a Hello first, got Value"),
        (Stats(), ErrorCode.UNEXPECTED, "expected a Hello first, got Stats"),
    ],
)
def test_refused_before_a_session(raw_tcp: Callable[..., Any], first: Any, code: ErrorCode,
                                  phrase: str) -> None:
    client = raw_tcp()
    client.send(first)
    got = client.wait_closed()
    assert len(got) == 1, got
    assert isinstance(got[0], ConnectError)
    assert got[0].code == code
    assert phrase in got[0].reason


def test_garbage_client_is_refused_and_others_keep_working(
    raw_tcp: Callable[..., Any], bridge: Callable[..., Any]
) -> None:
    sub_bridge = bridge()
    pub_bridge = bridge()
    inbox = sub_bridge.subscribe("/still/works", F64, transport="tcp", blocking=True,
                                 buffer_size=16)
    out = pub_bridge.publish("/still/works", F64, transport="tcp")
    bystander = raw_tcp()
    bystander.hello("bystander")

    web = raw_tcp()
    web.send_bytes(b"GET / HTTP/1.1\r\nHost: localhost\r\n\r\n")
    got = web.wait_closed()
    assert len(got) == 1, got
    assert isinstance(got[0], ConnectError)
    assert got[0].code == ErrorCode.MALFORMED
    assert "bad magic b'GE'" in got[0].reason
    assert "rlbridge protocol" in got[0].reason

    out.write(4.25)
    assert inbox.read(timeout=10) == 4.25
    body = bystander.stats()
    assert body["server"]["malformed"] == 1
    assert body["session"]["state"] == "connected"


def test_unsupported_frame_version_is_refused(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.send_bytes(FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION + 4, 0, 1) + b"\xc0")
    got = client.wait_closed()
    assert isinstance(got[0], ConnectError)
    assert got[0].code == ErrorCode.UNSUPPORTED_VERSION
    assert f"protocol version {PROTOCOL_VERSION + 4} is not supported" in got[0].reason


def test_oversized_frame_closes_the_session(make_server: Callable[..., ServerThread],
                                            raw_tcp: Callable[..., Any]) -> None:
    srv = make_server(max_packet=2048)
    client = raw_tcp(srv.port)
    ack = client.hello()
    assert ack.limits.max_packet == 2048
    client.send_bytes(FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, 4096))
    got = client.wait_closed()
    # Inside a session the answer is Error(code) and Disconnect, not ConnectError.
    errors = [p for p in got if isinstance(p, Error)]
    assert len(errors) == 1, got
    assert any(isinstance(p, Disconnect) for p in got), got
    assert errors[0].code == ErrorCode.TOO_LARGE
    assert "exceeds the limit of 2048 bytes" in errors[0].reason
    other = raw_tcp(srv.port)
    other.hello()
    assert other.stats()["server"]["malformed"] == 1


def frame(body: bytes) -> bytes:
    return FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, len(body)) + body


def test_malformed_packet_in_a_session_is_answered_and_the_session_goes_on(
    raw_tcp: Callable[..., Any],
) -> None:
    client = raw_tcp()
    client.hello()
    # A Batch whose stamps and values differ in length, an unknown tag, a string for an int.
    for body, phrase in [
        (b"\x95\x09\x01\x00\x92\x01\x02\x91\xcb" + b"\x00" * 8, "1 values but 2 stamps"),
        (b"\x92\x63\x01", "Invalid value 99"),
        (b"\x95\x08\xa3one\x00\x00\xc0", "Expected `int`, got `str`"),
    ]:
        client.send_bytes(frame(body))
        err = client.expect(Error)
        assert err.code == ErrorCode.MALFORMED
        assert phrase in err.reason
    client.send(TopicConnect(1, "publish", "/after/garbage", F64, transport="tcp"))
    assert client.expect(TopicAck).channel == 1
    body = client.stats()
    assert body["session"]["malformed"] == 3
    assert body["server"]["malformed"] == 3


def test_value_frames_of_one_read_count_and_answer_as_if_each_came_alone(
    raw_tcp: Callable[..., Any],
) -> None:
    """Values that arrive together (one read: the server hands them on as one run) are
    published, refused and counted one frame at a time."""
    client = raw_tcp()
    client.hello()
    client.send(TopicConnect(1, "publish", "/run/of/values", F64, transport="tcp"))
    client.expect(TopicAck)
    codec = PacketCodec()
    frames = [Value(1, 0, 0, 0.5), Value(1, 1, 0, 1.5), Value(1, 2, 0, "not a float"),
              Value(9, 0, 0, 1.0), Value(1, 3, 0, 2.5), Malformed, Value(1, 4, 0, 3.5)]
    before = client.stats()["session"]["packets_in"]
    client.send_bytes(b"".join(frame(b"\x92\x63\x01") if f is Malformed
                               else codec.encode_frame(f) for f in frames))
    answers = [client.expect(Error) for _ in range(3)]
    assert [(e.code, e.channel) for e in answers] == [
        (ErrorCode.BAD_VALUE, 1), (ErrorCode.UNKNOWN_CHANNEL, 9), (ErrorCode.MALFORMED, 1)]
    body = client.stats()
    assert body["session"]["packets_in"] - before == 6 + 1  # the frames but the bad one, stats
    channel = body["session"]["channels"]["1"]
    assert (channel["values_in"], channel["bad_values"]) == (4, 1)


def test_malformed_packet_before_hello_closes(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.send_bytes(frame(b"\x92\x63\x01"))
    got = client.wait_closed()
    assert isinstance(got[0], ConnectError)
    assert got[0].code == ErrorCode.MALFORMED


def test_client_disconnect_ends_the_session(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.hello("leaver")
    client.send(TopicConnect(1, "subscribe", "/left/behind", F64, transport="tcp"))
    client.expect(TopicAck)
    client.send(Disconnect(0, "bye"))
    client.wait_closed()
    watcher = raw_tcp()
    watcher.hello()
    body = watcher.stats()
    # The leaver's subscription went with it, so the topic is forgotten.
    assert ["/left/behind", F64] not in body["topics"]


def test_dropped_connection_releases_the_bindings(raw_tcp: Callable[..., Any],
                                                  wait_until: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.hello()
    client.send(TopicConnect(1, "publish", "/abandoned", F64, transport="tcp"))
    client.expect(TopicAck)
    watcher = raw_tcp()
    watcher.hello()
    assert ["/abandoned", F64] in watcher.stats()["topics"]
    client.close()
    wait_until(lambda: ["/abandoned", F64] not in watcher.stats()["topics"],
               what="the abandoned topic to go away")


def test_malformed_packet_names_its_channel(raw_tcp: Callable[..., Any]) -> None:
    """A body that starts ``[tag, channel, ...]`` is answered for that channel (spec 15.1)."""
    client = raw_tcp()
    client.hello()
    client.send_bytes(frame(b"\x95\x08\x05\xa1x\x00\x01"))  # Value(5, seq="x", ...)
    err = client.expect(Error)
    assert (err.code, err.channel) == (ErrorCode.MALFORMED, 5)
    assert "Expected `int`, got `str`" in err.reason
    # A broken topic-connect gets a TopicError, so a client waiting for channel 6 hears back.
    client.send_bytes(frame(b"\x95\x04\x06\xa4both\xa2/t\xb4std_msgs/msg/Float64"))
    refused = client.expect(TopicError)
    assert (refused.channel, refused.code) == (6, ErrorCode.MALFORMED)
    assert "both" in refused.reason
    client.send(TopicConnect(6, "publish", "/t", F64, transport="tcp"))
    assert client.expect(TopicAck).channel == 6


def test_session_limit(make_server: Callable[..., ServerThread], raw_tcp: Callable[..., Any],
                       raw_udp: Callable[..., Any]) -> None:
    srv = make_server(max_sessions=2)
    raw_tcp(srv.port).hello("one")
    raw_tcp(srv.port).hello("two")
    third = raw_tcp(srv.port)
    third.send(Hello(PROTOCOL_VERSION, "three"))
    got = third.wait_closed()
    assert isinstance(got[0], ConnectError), got
    assert got[0].code == ErrorCode.LIMIT
    assert "2 sessions" in got[0].reason
    over_udp = raw_udp(srv.port)
    over_udp.send(Hello(PROTOCOL_VERSION, "four"), token=0)
    token, refused = over_udp.recv_datagram()
    assert isinstance(refused, ConnectError)
    assert (token, refused.code) == (0, ErrorCode.LIMIT)
