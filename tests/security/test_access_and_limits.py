"""Allow-list of client networks and every server limit, each exceeded against a live server."""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable
from typing import Any

import pytest

from rlbridge import ErrorCode, Tuning
from rlbridge.csp.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.server.access import AllowList, KeyStore
from rlbridge.server.ratelimit import RateLimiter
from rlbridge.wire import (
    DATAGRAM_HEADER,
    MAGIC,
    PROTOCOL_VERSION,
    Batch,
    ConnectError,
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

F64 = "std_msgs/msg/Float64"
WAIT = 10.0
OTHER_HOST = "127.0.0.2"  # a loopback address the allow-lists below leave out


def counters(srv: ServerThread) -> dict[str, int]:
    assert srv.server.registry is not None
    return dict(srv.server.registry.ctx.counters)


# -- allow-list ----------------------------------------------------------------------------


def test_allow_list_unit() -> None:
    allow = AllowList(["192.168.1.0/24", "127.0.0.1", "fd00::/8"])
    assert allow.allows("192.168.1.77")
    assert allow.allows("127.0.0.1")
    assert allow.allows("::ffff:127.0.0.1")  # an IPv4 client on a dual-stack socket
    assert allow.allows("fd00::1%lo")
    assert not allow.allows("127.0.0.2")
    assert not allow.allows("192.168.2.1")
    assert not allow.allows("not an address")
    assert AllowList([]).allows("8.8.8.8")  # empty: everyone


def test_tcp_from_outside_the_allow_list_is_refused(make_server: Callable[..., ServerThread],
                                                    ) -> None:
    srv = make_server(allow=("127.0.0.1/32",))
    with socket.create_connection(("127.0.0.1", srv.port), timeout=WAIT,
                                  source_address=(OTHER_HOST, 0)) as sock:
        decoder = FrameDecoder()
        got: list[Any] = []
        while data := sock.recv(65536):
            got += decoder.feed(data)
    assert len(got) == 1
    assert isinstance(got[0], ConnectError)
    assert got[0].code == ErrorCode.NOT_ALLOWED
    assert OTHER_HOST in got[0].reason
    # From an allowed address everything works.
    with Bridge.connect("127.0.0.1", srv.port, timeout=WAIT) as bridge:
        assert bridge.server_stats()["server"]["not_allowed"] == 1


def test_udp_from_outside_the_allow_list_is_dropped(make_server: Callable[..., ServerThread],
                                                    ) -> None:
    srv = make_server(allow=("127.0.0.1",))
    codec = PacketCodec()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((OTHER_HOST, 0))
        sock.connect(("127.0.0.1", srv.port))
        for _ in range(3):
            sock.send(codec.encode_datagram(Hello(PROTOCOL_VERSION, "outsider"), 0))
        sock.settimeout(0.5)
        with Bridge.connect("127.0.0.1", srv.port, tuning=Tuning(control="udp"), timeout=WAIT):
            pass  # an allowed UDP client gets in
        with pytest.raises(TimeoutError):
            sock.recv(65536)  # never answered
    assert counters(srv)["udp_not_allowed"] == 3
    assert counters(srv)["sessions_opened"] == 1


def test_bad_allow_entry_is_a_config_error(cli: Any) -> None:
    result = cli.run("serve", "--allow", "192.168.1.0/33", "--port", "0")
    assert result.returncode == 2
    assert "192.168.1.0/33" in result.stderr
    assert "is not a network" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_missing_key_file_is_one_line(cli: Any, tmp_path: Any) -> None:
    result = cli.run("serve", "--psk-file", str(tmp_path / "nope"), "--port", "0")
    assert result.returncode == 1
    assert "cannot read the key file" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_key_store_parse_errors() -> None:
    key = "ab" * 16
    assert KeyStore.parse(f"{key}\nbob {'cd' * 16}\n", "f").key_for("bob") == bytes.fromhex(
        "cd" * 16)
    for text, message in [
        (f"{key}\n{key}\n", "line 2: a second default key"),
        (f"bob {key}\nbob {key}\n", "line 2: a second line for client 'bob'"),
        ("a b c\n", "line 1: expected"),
        (f"bob {key} publish=/a stats=maybe\n", "stats= takes 'all' or 'own'"),
        (f"bob {key} publish=/a publish=/b\n", "repeated option 'publish'"),
        (f"bob {key} write=/a\n", "unknown or repeated option 'write'"),
        ("bob not-hex\n", "line 1: a key must be written in hex"),
        ("bob -\n", "no key in the file"),
        ("# nothing\n", "no key in the file"),
    ]:
        with pytest.raises(ValueError, match=message):
            KeyStore.parse(text, "f")


# -- limits --------------------------------------------------------------------------------


def test_oversized_datagram_is_dropped_and_counted(make_server: Callable[..., ServerThread],
                                                   raw_udp: Callable[..., Any]) -> None:
    srv = make_server(max_packet=1024)
    client = raw_udp(srv.port)
    client.hello()
    client.send(TopicConnect(1, "publish", "/big", "std_msgs/msg/String", transport="udp"))
    assert isinstance(client.expect(TopicAck), TopicAck)
    client.send(Value(1, 0, 0, "x" * 2000))
    client.send(Value(1, 1, 0, "x" * 900))  # under the limit: accepted
    client.send(Stats())
    body = client.expect(Stats).body
    assert body["server"]["udp_too_large"] == 1
    assert body["session"]["channels"]["1"]["values_in"] == 1


def test_topic_name_length_limit(make_server: Callable[..., ServerThread],
                                 raw_tcp: Callable[..., Any]) -> None:
    srv = make_server(max_topic_length=10)
    client = raw_tcp(srv.port)
    client.hello()
    client.send(TopicConnect(1, "publish", "/" + "a" * 10, F64))
    refused = client.expect(TopicError)
    assert (refused.channel, refused.code) == (1, ErrorCode.LIMIT)
    assert "11 characters" in refused.reason
    assert "limit of 10" in refused.reason
    client.send(TopicConnect(2, "publish", "/" + "a" * 9, F64))
    assert client.expect(TopicAck).channel == 2


def test_topic_name_over_the_protocol_cap_is_malformed(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.hello()
    client.send(TopicConnect(3, "publish", "/" + "a" * 300, F64))
    refused = client.expect(TopicError)
    assert (refused.channel, refused.code) == (3, ErrorCode.MALFORMED)
    client.send(Stats())  # the session goes on
    assert isinstance(client.expect(Stats), Stats)


def test_rate_limiter_with_a_fake_clock() -> None:
    limiter = RateLimiter(100.0, now_ns=0)
    assert limiter.admit(150, 0) == 100  # a full bucket: one second's worth
    assert limiter.dropped == 50
    assert limiter.admit(1, 1_000_000) == 0  # 1 ms later: 0.1 of a token
    assert limiter.admit(10, 101_000_000) == 10  # 0.1 s later: 10 tokens
    assert limiter.admit(1000, 100 * 10**9) == 100  # long idle: still capped at the bucket
    assert limiter.should_warn(100 * 10**9)
    assert not limiter.should_warn(100 * 10**9 + 999_999_999)
    assert limiter.should_warn(101 * 10**9)
    with pytest.raises(ValueError, match="positive"):
        RateLimiter(0, 0)


def test_values_over_the_rate_are_dropped_counted_and_reported_once_a_second(
        make_server: Callable[..., ServerThread], raw_tcp: Callable[..., Any]) -> None:
    srv = make_server(max_rate=50.0)
    client = raw_tcp(srv.port)
    client.hello()
    client.send(TopicConnect(1, "publish", "/rate", F64))
    assert isinstance(client.expect(TopicAck), TopicAck)
    start = time.monotonic()
    client.send(Batch(1, 0, [0] * 100, [float(i) for i in range(100)]))
    client.send(*(Value(1, 100 + i, 0, float(i)) for i in range(400)))
    client.send(Stats())
    errors: list[Error] = []
    while not isinstance(packet := client.recv(), Stats):
        assert isinstance(packet, Error), packet
        errors.append(packet)
    elapsed = time.monotonic() - start
    session, server = packet.body["session"], packet.body["server"]
    values_in = session["channels"]["1"]["values_in"]
    assert values_in + server["rate_dropped"] == 500  # every value passed or was counted
    assert 50 <= values_in <= 50 + 50 * elapsed + 1
    assert 1 <= len(errors) <= 1 + math.ceil(elapsed)  # not one per dropped value
    assert all(e.code == ErrorCode.LIMIT and e.channel == 1 for e in errors)
    assert "50 values per second" in errors[0].reason


def test_datagram_header_only_and_garbage_under_limits(raw_udp: Callable[..., Any],
                                                       server: ServerThread) -> None:
    """Header-only datagrams and a huge token do not open or disturb anything."""
    client = raw_udp()
    client.send_bytes(DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, 0))
    client.send_bytes(DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0xFF, 2**64 - 1))
    client.hello()
    client.send(Stats())
    body = client.expect(Stats).body["server"]
    assert body["udp_malformed"] == 1
    assert body["udp_bad_token"] == 1
