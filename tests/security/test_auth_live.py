"""Pre-shared keys and sealed datagrams against a live server, through the SDK and raw sockets."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from rlbridge import ConnectionFailed, ErrorCode, Psk, Tuning
from rlbridge.csp.auth import AuthRefused, ClientAuth
from rlbridge.csp.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.wire import (
    PROTOCOL_VERSION,
    AuthChallenge,
    AuthProof,
    ConnectAck,
    ConnectError,
    Heartbeat,
    Hello,
    Packet,
    PacketCodec,
    Stats,
    TopicAck,
    TopicConnect,
    Value,
)
from rlbridge.wire.auth import SealedCodec

F64 = "std_msgs/msg/Float64"
KEY = bytes(range(32))
ALICE = bytes(range(100, 132))
WAIT = 10.0


@pytest.fixture
def key_file(tmp_path: Path) -> Path:
    path = tmp_path / "keys"
    path.write_text(f"# default key\n{KEY.hex()}\nalice {ALICE.hex()}  # her own\n")
    return path


@pytest.fixture
def psk_server(make_server: Callable[..., ServerThread], key_file: Path) -> ServerThread:
    return make_server(psk_file=key_file)


def counters(srv: ServerThread) -> dict[str, int]:
    """The server's counters, read from the test thread (plain ints in a dict)."""
    assert srv.server.registry is not None
    return dict(srv.server.registry.ctx.counters)


@pytest.mark.parametrize("control", ["tcp", "udp"])
def test_right_key_moves_values_over_tcp_and_sealed_udp(psk_server: ServerThread,
                                                        control: Any) -> None:
    port = psk_server.port
    with Bridge.connect("127.0.0.1", port, security=Psk(key=KEY), tuning=Tuning(control=control),
                        timeout=WAIT) as pub, \
            Bridge.connect("127.0.0.1", port, security=Psk(key=KEY),
                           tuning=Tuning(control=control), timeout=WAIT) as sub:
        channels = [("udp", "/sealed")] + ([("tcp", "/plain")] if control == "tcp" else [])
        for transport, topic in channels:
            inbox = sub.subscribe(topic, F64, transport=transport, blocking=True,
                                  buffer_size=64)
            out = pub.publish(topic, F64, transport=transport)
            for i in range(20):
                out.write(float(i))
            assert [inbox.read(timeout=WAIT) for _ in range(20)] == [float(i) for i in range(20)]
        assert pub._conn.datagrams_dropped == {}
        assert sub._conn.datagrams_dropped == {}
    got = counters(psk_server)
    assert got["sessions_authenticated"] == 2
    assert got.get("auth_failed", 0) == 0
    assert not any(k in got for k in ("udp_bad_mac", "udp_replayed", "udp_unsealed"))


@pytest.mark.parametrize("control", ["tcp", "udp"])
def test_wrong_key_is_refused_and_counted(psk_server: ServerThread, control: Any) -> None:
    with pytest.raises(AuthRefused) as exc:
        Bridge.connect("127.0.0.1", psk_server.port, security=Psk(key=b"w" * 32),
                       tuning=Tuning(control=control),
                       timeout=WAIT)
    assert exc.value.code == ErrorCode.AUTH_FAILED
    assert "could not prove it knows the pre-shared key" in str(exc.value)
    assert isinstance(exc.value, ConnectionFailed)  # the session did not open
    # The client refused first and told the server why: it counts the failure too.
    deadline = time.monotonic() + WAIT
    while counters(psk_server).get("auth_failed", 0) < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert counters(psk_server)["auth_failed"] == 1
    assert len(psk_server.server.registry or []) == 0


def test_server_counts_a_wrong_proof(psk_server: ServerThread) -> None:
    """A client that answers the challenge with garbage gets AUTH_FAILED and is closed."""
    with socket.create_connection(("127.0.0.1", psk_server.port), timeout=WAIT) as sock:
        codec = PacketCodec()
        auth = ClientAuth(KEY, "liar")
        sock.sendall(codec.encode_frame(Hello(PROTOCOL_VERSION, "liar", auth.nonce)))
        challenge = read_frames(sock, codec)[0]
        assert isinstance(challenge, AuthChallenge)
        sock.sendall(codec.encode_frame(AuthProof(bytes(32))))
        refused = read_frames(sock, codec)
    assert isinstance(refused[0], ConnectError)
    assert refused[0].code == ErrorCode.AUTH_FAILED
    assert "proof does not match" in refused[0].reason
    assert counters(psk_server)["auth_failed"] == 1


@pytest.mark.parametrize("control", ["tcp", "udp"])
def test_no_key_when_one_is_required(psk_server: ServerThread, control: Any,
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("RLBRIDGE_PSK", raising=False)
    with pytest.raises(AuthRefused, match="requires a pre-shared key") as exc:
        Bridge.connect("127.0.0.1", psk_server.port, tuning=Tuning(control=control), timeout=WAIT)
    assert exc.value.code == ErrorCode.AUTH_FAILED
    assert counters(psk_server)["auth_failed"] == 1


def test_per_client_keys(psk_server: ServerThread) -> None:
    port = psk_server.port
    with Bridge.connect("127.0.0.1", port, name="alice", security=Psk(key=ALICE), timeout=WAIT):
        pass
    with pytest.raises(AuthRefused):  # alice may not use the default key
        Bridge.connect("127.0.0.1", port, name="alice", security=Psk(key=KEY), timeout=WAIT)
    with pytest.raises(AuthRefused):  # nor anyone else alice's
        Bridge.connect("127.0.0.1", port, name="bob", security=Psk(key=ALICE), timeout=WAIT)


def test_only_named_clients_without_a_default_key(make_server: Callable[..., ServerThread],
                                                  tmp_path: Path) -> None:
    path = tmp_path / "keys"
    path.write_text(f"alice {ALICE.hex()}\n")
    srv = make_server(psk_file=path)
    with pytest.raises(AuthRefused, match="no pre-shared key for client name 'bob'"):
        Bridge.connect("127.0.0.1", srv.port, name="bob", security=Psk(key=ALICE), timeout=WAIT)


def test_key_from_the_environment_and_from_a_file(psk_server: ServerThread, tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RLBRIDGE_PSK", KEY.hex())
    with Bridge.connect("127.0.0.1", psk_server.port, timeout=WAIT) as b:
        assert b._conn.codec.__class__ is SealedCodec
    monkeypatch.delenv("RLBRIDGE_PSK")
    path = tmp_path / "client.key"
    path.write_text(ALICE.hex() + "\n")
    with Bridge.connect("127.0.0.1", psk_server.port, name="alice", security=Psk(file=path),
                        timeout=WAIT):
        pass


def test_server_key_from_the_environment(make_server: Callable[..., ServerThread],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RLBRIDGE_PSK", KEY.hex())
    srv = make_server()
    monkeypatch.delenv("RLBRIDGE_PSK")
    with pytest.raises(AuthRefused):
        Bridge.connect("127.0.0.1", srv.port, timeout=WAIT)
    with Bridge.connect("127.0.0.1", srv.port, security=Psk(key=KEY), timeout=WAIT):
        pass


def test_client_with_a_key_refuses_an_unauthenticated_server(server: ServerThread) -> None:
    """No silent downgrade: a key given means the server must prove it."""
    with pytest.raises(AuthRefused, match="without authenticating"):
        Bridge.connect("127.0.0.1", server.port, security=Psk(key=KEY), timeout=WAIT)


def test_bad_keys_are_clear_errors(make_server: Callable[..., ServerThread], tmp_path: Path,
                                   server: ServerThread) -> None:
    from rlbridge.server import ServerError

    path = tmp_path / "keys"
    path.write_text("alice 0011\n")
    with pytest.raises(ServerError, match=r"keys, line 1: key of 2 bytes is too short"):
        make_server(psk_file=path)
    with pytest.raises(ServerError, match="cannot read the key file"):
        make_server(psk_file=tmp_path / "missing")
    with pytest.raises(ValueError, match="too short"):
        Bridge.connect("127.0.0.1", server.port, security=Psk(key=b"short"), timeout=WAIT)


# -- sealed datagrams on the wire ----------------------------------------------------------


class SealedUdp:
    """A raw UDP client that authenticates, then sends sealed datagrams it controls."""

    def __init__(self, port: int, key: bytes = KEY, name: str = "raw") -> None:
        self.plain = PacketCodec()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect(("127.0.0.1", port))
        self.sock.settimeout(WAIT)
        auth = ClientAuth(key, name)
        self.sock.send(self.plain.encode_datagram(Hello(PROTOCOL_VERSION, name, auth.nonce), 0))
        challenge = self.plain.decode_datagram(self.sock.recv(65536))[2]
        assert isinstance(challenge, AuthChallenge), challenge
        self.sock.send(self.plain.encode_datagram(auth.answer(challenge, self.sock), 0))
        ack = auth.decode(self.plain, self.sock.recv(65536))
        assert isinstance(ack, ConnectAck), ack
        self.ack = ack
        self.codec = auth.sealed(ack)

    def seal(self, packet: Packet) -> bytes:
        return self.codec.encode_datagram(packet, self.ack.token)

    def request(self, packet: Packet) -> Packet:
        self.sock.send(self.seal(packet))
        while True:
            got = self.codec.decode_datagram(self.sock.recv(65536))[2]
            if not isinstance(got, Heartbeat):
                return got

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def sealed_udp(psk_server: ServerThread) -> Iterator[Callable[..., SealedUdp]]:
    made: list[SealedUdp] = []

    def make(**kwargs: Any) -> SealedUdp:
        made.append(SealedUdp(psk_server.port, **kwargs))
        return made[-1]

    yield make
    for client in made:
        client.close()


def test_forged_replayed_reordered_truncated_and_unsealed_datagrams(
        psk_server: ServerThread, sealed_udp: Callable[..., SealedUdp]) -> None:
    client = sealed_udp()
    ack = client.request(TopicConnect(1, "publish", "/f", F64, transport="udp"))
    assert isinstance(ack, TopicAck)
    good = client.seal(Value(1, 0, 0, 1.0))
    client.sock.send(good)
    client.sock.send(good)  # replayed
    client.sock.send(good[:-1] + bytes([good[-1] ^ 1]))  # forged tag
    client.sock.send(client.plain.encode_datagram(Value(1, 1, 0, 2.0), client.ack.token))
    later, earlier = client.seal(Value(1, 1, 0, 2.0)), client.seal(Value(1, 2, 0, 3.0))
    client.sock.send(earlier)  # reordered: both arrive once, in the other order
    client.sock.send(later)
    client.sock.send(later)  # and a copy of one of them: replayed
    truncated = client.seal(Value(1, 3, 0, 4.0))
    client.sock.send(truncated[:-1])  # tag cut short: does not open
    client.sock.send(truncated[:30])  # shorter than any seal
    body = client.request(Stats())
    assert isinstance(body, Stats)
    server = body.body["server"]
    assert (server["udp_replayed"], server["udp_bad_mac"], server["udp_unsealed"]) == (2, 2, 2)
    channel = body.body["session"]["channels"]["1"]
    # Only the genuine ones got past the seal, each once (the reordered one arrives late).
    assert (channel["values_in"], channel["late"]) == (2, 1)


def test_udp_hello_retransmission_and_stray_proofs(psk_server: ServerThread) -> None:
    plain = PacketCodec()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.connect(("127.0.0.1", psk_server.port))
        sock.settimeout(WAIT)
        sock.send(plain.encode_datagram(AuthProof(bytes(32)), 0))  # no challenge outstanding
        auth = ClientAuth(KEY, "again")
        hello = plain.encode_datagram(Hello(PROTOCOL_VERSION, "again", auth.nonce), 0)
        sock.send(hello)
        first = plain.decode_datagram(sock.recv(65536))[2]
        sock.send(hello)  # the challenge was "lost": the same one comes again
        second = plain.decode_datagram(sock.recv(65536))[2]
        assert first == second
        assert isinstance(first, AuthChallenge)
        proof = plain.encode_datagram(auth.answer(first, sock), 0)
        sock.send(proof)
        ack = auth.decode(plain, sock.recv(65536))
        assert isinstance(ack, ConnectAck)
        sock.send(proof)  # the ack was "lost": the same proof gets the same session again
        again = auth.decode(plain, sock.recv(65536))
        while isinstance(again, Heartbeat):  # the session is live and sends heartbeats
            again = auth.decode(plain, sock.recv(65536))
        assert isinstance(again, ConnectAck)
        assert again.token == ack.token
        sock.send(plain.encode_datagram(AuthProof(bytes(32)), 0))  # another proof: refused
        # The client restarts on the same address and name: a new nonce, a new handshake.
        fresh = ClientAuth(KEY, "again")
        sock.send(plain.encode_datagram(Hello(PROTOCOL_VERSION, "again", fresh.nonce), 0))
        challenge = auth.decode(plain, sock.recv(65536))  # the old session's heartbeats
        while isinstance(challenge, Heartbeat):           # are sealed with its keys
            challenge = auth.decode(plain, sock.recv(65536))
        assert isinstance(challenge, AuthChallenge)
        assert challenge != first
    assert counters(psk_server)["udp_unexpected_proof"] == 2


def read_frames(sock: socket.socket, codec: PacketCodec) -> list[Any]:
    """Packets until at least one arrived (or the peer closed)."""
    from rlbridge.wire import FrameDecoder

    decoder = FrameDecoder(codec)
    while True:
        data = sock.recv(65536)
        got = decoder.feed(data)
        if got or not data:
            return got
