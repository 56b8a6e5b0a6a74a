"""Malformed input the other suites leave out: each answered or dropped, never a stuck session."""

from __future__ import annotations

import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import pytest

from rlbridge import ErrorCode
from rlbridge.server import ServerThread, tcp
from rlbridge.wire import (
    FRAME_HEADER,
    MAGIC,
    PROTOCOL_VERSION,
    AuthChallenge,
    AuthProof,
    ConnectError,
    Error,
    Hello,
    Stats,
    TopicAck,
    TopicConnect,
)

F64 = "std_msgs/msg/Float64"
KEY = bytes(range(32))


def frame(body: bytes) -> bytes:
    return FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, len(body)) + body


def counters(srv: ServerThread) -> dict[str, int]:
    assert srv.server.registry is not None
    return dict(srv.server.registry.ctx.counters)


@pytest.mark.parametrize(("body", "phrase"), [
    (b"\xc1", "not a packet"),  # a byte MessagePack never uses
    (b"\x95\x08\x01\x00\x00" + b"\x91" * 5000 + b"\x01", "nested too deeply"),
    (msgspec.msgpack.encode([20, 1, "s" * 5000, "std_srvs/srv/Trigger", {}]),
     "Expected `str` of length <= 256"),
    (msgspec.msgpack.encode([8, 1, 0]), "Expected `array` of at least length 5"),
    (msgspec.msgpack.encode([8, 1, 0, 2**64 - 1, 1.0]), "Expected `int` <= 9223372036854775807"),
    (b"", "not a packet"),
])
def test_bad_bodies_in_a_session(raw_tcp: Callable[..., Any], body: bytes, phrase: str) -> None:
    client = raw_tcp()
    client.hello()
    client.send_bytes(frame(body))
    err = client.expect(Error)
    assert err.code == ErrorCode.MALFORMED
    assert phrase in err.reason, err.reason
    client.send(TopicConnect(1, "publish", "/still/alive", F64))
    assert client.expect(TopicAck).channel == 1


def test_huge_client_name_is_refused_before_a_session(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.send_bytes(frame(msgspec.msgpack.encode([1, 1, "n" * 10_000])))
    got = client.wait_closed()
    assert isinstance(got[0], ConnectError)
    assert got[0].code == ErrorCode.MALFORMED
    assert "length <= 128" in got[0].reason


@pytest.mark.parametrize("packet", [AuthChallenge(b"n" * 16, b"p" * 32), AuthProof(b"p" * 32)])
def test_auth_packets_inside_a_session_are_unexpected(raw_tcp: Callable[..., Any],
                                                      packet: Any) -> None:
    client = raw_tcp()
    client.hello()
    client.send(packet)
    err = client.expect(Error)
    assert err.code == ErrorCode.UNEXPECTED
    assert type(packet).__name__ in err.reason
    assert isinstance(client.stats(), dict)


def test_proof_without_a_challenge_is_refused(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.send(AuthProof(b"p" * 32))
    got = client.wait_closed()
    assert isinstance(got[0], ConnectError)
    assert got[0].code == ErrorCode.UNEXPECTED
    assert "expected a Hello first, got AuthProof" in got[0].reason


def test_second_hello_instead_of_the_proof(make_server: Callable[..., ServerThread],
                                           raw_tcp: Callable[..., Any], tmp_path: Path) -> None:
    keys = tmp_path / "k"
    keys.write_text(KEY.hex())
    srv = make_server(psk_file=keys)
    client = raw_tcp(srv.port)
    client.send(Hello(PROTOCOL_VERSION, "x", b"n" * 16))
    assert isinstance(client.expect(AuthChallenge), AuthChallenge)
    client.send(Hello(PROTOCOL_VERSION, "x", b"n" * 16))
    got = client.wait_closed()
    assert isinstance(got[0], ConnectError)
    assert "expected an AuthProof, got Hello" in got[0].reason
    assert len(srv.server.registry or []) == 0


@pytest.mark.parametrize("keyed", [False, True])
def test_unfinished_hello_is_closed_after_the_deadline(
        make_server: Callable[..., ServerThread], raw_tcp: Callable[..., Any], tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch, keyed: bool) -> None:
    """Half a header, or a hello whose proof never comes: the socket does not stay forever."""
    monkeypatch.setattr(tcp, "HELLO_TIMEOUT", 0.5)
    keys = tmp_path / "k"
    keys.write_text(KEY.hex())
    srv = make_server(**({"psk_file": keys} if keyed else {}))
    client = raw_tcp(srv.port)
    if keyed:
        client.send(Hello(PROTOCOL_VERSION, "slow", b"n" * 16))
        assert isinstance(client.expect(AuthChallenge), AuthChallenge)
    else:
        client.send_bytes(b"RB\x01")
    got = client.wait_closed()
    assert isinstance(got[-1], ConnectError)
    assert "no complete hello within 0.5 s" in got[-1].reason
    assert counters(srv)["handshake_timeouts"] == 1


def test_truncated_frame_then_close_ends_the_session(server: ServerThread,
                                                     raw_tcp: Callable[..., Any],
                                                     wait_until: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.hello()
    client.send(TopicConnect(1, "publish", "/cut", F64))
    client.expect(TopicAck)
    whole = frame(msgspec.msgpack.encode([8, 1, 0, 0, 1.0]))
    client.send_bytes(whole[:-3])  # the rest never comes
    client.sock.shutdown(socket.SHUT_WR)
    assert client.wait_closed() == []
    registry = server.server.registry
    assert registry is not None
    wait_until(lambda: len(registry) == 0, what="the session to close")


def test_many_bad_datagrams_do_not_disturb_a_session(raw_udp: Callable[..., Any]) -> None:
    client = raw_udp()
    client.hello()
    for i in range(200):
        client.send_bytes(bytes([i]) * (i + 1))
    client.send(Stats())
    body = client.expect(Stats).body
    assert body["server"]["udp_malformed"] == 200
    assert body["session"]["malformed"] == 0  # none of them could claim to be this session


def test_shutdown_closes_connections_still_in_their_hello(
        make_server: Callable[..., ServerThread], raw_tcp: Callable[..., Any],
        wait_until: Callable[..., Any]) -> None:
    srv = make_server()
    client = raw_tcp(srv.port)
    client.send_bytes(b"RB")  # half a header, then nothing
    registry = srv.server.registry
    assert registry is not None
    wait_until(lambda: len(registry.ctx.handshaking) == 1, what="the server to accept")
    srv.stop()
    assert client.wait_closed() == []  # closed by the server, not left to the loop's end
