"""UDP on a live server: UDP-only sessions, tokens, dropped datagrams, the watchdog."""

from __future__ import annotations

import secrets
from collections.abc import Callable
from typing import Any

import msgspec
import pytest

from rlbridge import ErrorCode
from rlbridge.adapters.base import QoS
from rlbridge.adapters.inproc import InProcessBus
from rlbridge.client.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.server.datagram_limit import too_large_answer
from rlbridge.wire import (
    DATAGRAM_HEADER,
    MAGIC,
    MAX_DATAGRAM,
    PROTOCOL_VERSION,
    ConnectAck,
    Disconnect,
    Error,
    GoalResult,
    Heartbeat,
    Hello,
    Packet,
    ServiceResult,
    Stats,
    TopicAck,
    TopicConnect,
    TopicError,
    Value,
)
from rlbridge.wire.link import LinkState

F64 = "std_msgs/msg/Float64"


def test_udp_only_session(raw_udp: Callable[..., Any], raw_tcp: Callable[..., Any]) -> None:
    client = raw_udp()
    ack = client.hello("udp-only")
    assert ack.token != 0
    client.send(TopicConnect(1, "subscribe", "/udp/only", F64, transport="udp"))
    assert client.expect(TopicAck) == TopicAck(1, F64, 0.0)
    client.send(Stats())
    body = client.expect(Stats).body
    assert body["session"]["session"] == ack.session
    assert body["session"]["name"] == "udp-only"

    publisher = raw_tcp()
    publisher.hello()
    publisher.send(TopicConnect(7, "publish", "/udp/only", F64, transport="tcp"))
    publisher.expect(TopicAck)
    publisher.send(Value(7, 0, 0, 2.5))
    token, value = client.recv_datagram()
    while isinstance(value, Heartbeat):
        token, value = client.recv_datagram()
    assert token == ack.token
    assert isinstance(value, Value)
    assert (value.channel, value.value) == (1, 2.5)


def test_tcp_channel_on_a_udp_only_session_is_refused(raw_udp: Callable[..., Any]) -> None:
    client = raw_udp()
    client.hello()
    client.send(TopicConnect(1, "subscribe", "/udp/tcp", F64, transport="tcp"))
    err = client.expect(TopicError)
    assert err.code == ErrorCode.TRANSPORT_DISABLED
    assert "without a TCP connection" in err.reason
    client.send(TopicConnect(2, "subscribe", "/udp/tcp", F64, transport="udp"))
    assert client.expect(TopicAck).channel == 2


def test_retransmitted_hello_gets_the_same_session(raw_udp: Callable[..., Any]) -> None:
    client = raw_udp()
    first = client.hello("twice")
    client.send(Hello(PROTOCOL_VERSION, "twice"), token=0)
    again = client.expect(ConnectAck)
    assert (again.session, again.token) == (first.session, first.token)
    client.send(Stats())
    assert client.expect(Stats).body["server"]["sessions_opened"] == 1
    # Another socket (another address) with the same name is another client.
    other = raw_udp()
    assert other.hello("twice").session != first.session


def test_hello_after_the_session_closed_gets_a_new_one(raw_udp: Callable[..., Any]) -> None:
    client = raw_udp()
    first = client.hello("again")
    client.send(Disconnect(0, "bye"))
    second = client.hello("again")
    assert second.session != first.session
    assert second.token != first.token


def test_wrong_tokens_are_dropped_counted_and_never_answered(
    raw_udp: Callable[..., Any], raw_tcp: Callable[..., Any]
) -> None:
    live = raw_udp()
    live_ack = live.hello("live")
    stranger = raw_udp()
    bogus = [t for t in (secrets.randbits(64) for _ in range(10)) if t not in (0, live_ack.token)]
    for token in bogus[:4]:
        stranger.send(Stats(), token=token)
        stranger.send(TopicConnect(1, "subscribe", "/x", F64, transport="udp"), token=token)
    # Token 0 with anything but a hello: dropped and counted too.
    stranger.send(Stats(), token=0)
    # Garbage: counted as malformed, not answered; an unknown token is checked before the
    # body (docs/protocol.md 3: the order of the checks), so a bad body under one counts there.
    stranger.send_bytes(b"not a datagram at all")
    stranger.send_bytes(DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, 5) + b"\xc1")
    # The first datagram the stranger ever gets is the answer to its hello: nothing before it.
    stranger.send(Hello(PROTOCOL_VERSION, "stranger"), token=0)
    token, first = stranger.recv_datagram()
    assert isinstance(first, ConnectAck), f"the server answered a bad datagram: {first!r}"
    assert token == first.token

    watcher = raw_tcp()
    watcher.hello()
    counters = watcher.stats()["server"]
    assert counters["udp_bad_token"] == 9
    assert counters["udp_no_token"] == 1
    assert counters["udp_malformed"] == 1
    assert counters["sessions_opened"] == 3  # live, stranger, watcher: nothing else


def test_token_of_a_closed_session_is_dead(raw_udp: Callable[..., Any]) -> None:
    client = raw_udp()
    ack = client.hello()
    client.send(Disconnect(0, "bye"))
    # From a fresh socket, so that nothing the old session sent can be mistaken for an answer.
    probe = raw_udp()
    probe.send(Stats(), token=ack.token)  # the old token is refused now
    probe.send(Hello(PROTOCOL_VERSION, "probe"), token=0)
    _token, first = probe.recv_datagram()
    assert isinstance(first, ConnectAck), first
    probe.token = first.token
    probe.send(Stats())
    assert probe.expect(Stats).body["server"]["udp_bad_token"] == 1


def test_watchdog_drops_a_silent_udp_session(make_server: Callable[..., ServerThread],
                                             raw_udp: Callable[..., Any]) -> None:
    srv = make_server(heartbeat_ms=50, timeout_ms=500)
    # An SDK client that sends heartbeats stays connected all the while.
    with Bridge.connect("127.0.0.1", srv.port, name="alive", timeout=10) as alive:
        silent = raw_udp(srv.port)
        ack = silent.hello("silent")
        assert ack.timeout_ms == 500
        packets = []
        while True:
            packet = silent.recv(skip=())
            packets.append(packet)
            if not isinstance(packet, Heartbeat):
                break
        bye = packets[-1]
        assert isinstance(bye, Disconnect), packets
        assert "watchdog" in bye.reason
        assert "500 ms" in bye.reason
        assert len(packets) >= 2, "the server sent no heartbeat before giving up"
        stats = alive.server_stats()
        assert stats["server"]["sessions_timed_out"] == 1
        assert stats["session"]["name"] == "alive"
        assert alive.link_state is not LinkState.LOST
        # The dead session's token is gone.
        silent.send(Stats(), token=ack.token)
        silent.send(Hello(PROTOCOL_VERSION, "back"), token=0)
        assert isinstance(silent.recv_datagram()[1], ConnectAck)


def test_watchdog_drops_a_silent_tcp_session(make_server: Callable[..., ServerThread],
                                             raw_tcp: Callable[..., Any]) -> None:
    srv = make_server(heartbeat_ms=50, timeout_ms=300)
    silent = raw_tcp(srv.port)
    silent.hello()
    got = silent.wait_closed()
    assert isinstance(got[-1], Disconnect), got
    assert "watchdog" in got[-1].reason


def test_udp_disabled_server_refuses_udp_channels(make_server: Callable[..., ServerThread],
                                                 raw_tcp: Callable[..., Any]) -> None:
    srv = make_server(udp=False)
    client = raw_tcp(srv.port)
    client.hello()
    client.send(TopicConnect(1, "subscribe", "/no/udp", F64, transport="udp"))
    err = client.expect(TopicError)
    assert err.code == ErrorCode.TRANSPORT_DISABLED
    assert "--no-udp" in err.reason


def test_malformed_datagram_with_a_live_token_is_answered(raw_udp: Callable[..., Any]) -> None:
    """A valid header and token prove the sender: it hears what was wrong (spec 15.1)."""
    client = raw_udp()
    ack = client.hello()
    header = DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, ack.token)
    client.send_bytes(header + b"\x95\x08\x03\xa1x\x00\x01")  # Value(3, seq="x", ...)
    err = client.expect(Error)
    assert (err.code, err.channel) == (ErrorCode.MALFORMED, 3)
    client.send_bytes(header + b"\x95\x04\x06\xa4both\xa2/t\xb4std_msgs/msg/Float64")
    refused = client.expect(TopicError)
    assert (refused.channel, refused.code) == (6, ErrorCode.MALFORMED)
    client.send(Stats())
    body = client.expect(Stats).body
    assert body["server"]["udp_malformed"] == 2
    assert body["session"]["malformed"] == 2


def test_a_stats_answer_too_large_for_a_datagram_is_refused_and_counted(
        server: ServerThread, raw_udp: Callable[..., Any], raw_tcp: Callable[..., Any],
        caplog: pytest.LogCaptureFixture) -> None:
    """The answer would be a datagram over 65 507 bytes, which no socket sends: it used to
    vanish (the client waited out its patience); now a small TOO_LARGE Error says to ask over
    TCP, the server counts it, and the session goes on."""
    registry = server.server.registry
    assert registry is not None
    bus = registry.ctx.adapter
    assert isinstance(bus, InProcessBus)
    for n in range(300):  # other nodes' topics, 250-character names: about 80 kB of list
        bus.create_publisher(f"/many/n{n:03d}/" + "t" * 240, F64, "data", QoS())
    client = raw_udp()
    client.hello("asks-over-udp")
    client.send(Stats())
    err = client.expect(Error)
    assert (err.code, err.channel) == (ErrorCode.TOO_LARGE, None)
    assert "ask over TCP" in err.reason
    client.send(TopicConnect(1, "subscribe", "/still/here", F64, transport="udp"))
    assert client.expect(TopicAck).channel == 1
    over_tcp = raw_tcp()
    over_tcp.hello()
    over_tcp.send(Stats())
    answer = over_tcp.expect(Stats)
    assert len(msgspec.msgpack.encode(answer)) > MAX_DATAGRAM  # it really could not fit
    assert answer.body["server"]["udp_too_large_out"] == 1
    told = [r.getMessage() for r in caplog.records if "does not fit a datagram" in r.getMessage()]
    assert len(told) == 1
    assert "a Stats of" in told[0]


@pytest.mark.parametrize(("packet", "answer"), [
    (Stats({"big": 1}), Error(3, "")),
    (ServiceResult(7, 0, {"big": 1}), ServiceResult(7, 3, None, "")),
    (GoalResult(4, 4, {"big": 1}), GoalResult(4, 0, None, "")),
    (TopicAck(4, F64), None),
])
def test_what_answers_in_place_of_a_packet_too_large(packet: Packet,
                                                    answer: Packet | None) -> None:
    got = too_large_answer(packet, 70_000)
    if answer is None:
        assert got is None
        return
    assert type(got) is type(answer)
    fields = msgspec.structs.asdict(got)
    assert "70000 bytes" in fields["reason"]
    assert {**fields, "reason": ""} == msgspec.structs.asdict(answer)
