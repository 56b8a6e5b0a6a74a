"""TLS on the TCP transport against a live server: trust, pinning, dates, mismatches, mTLS.

Every refusal must be one clear sentence on the client, come within the connect timeout (no
hang), and leave the server serving: a session opened before the bad attempts keeps moving
values after them.
"""

from __future__ import annotations

import datetime
import socket
import ssl
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from rlbridge import Psk, Tls, TlsFailed
from rlbridge.csp.auth import AuthRefused
from rlbridge.csp.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.tls.certs import Issued, init_server, issue, make_ca
from rlbridge.wire import PROTOCOL_VERSION, ConnectError, Hello, PacketCodec, Value
from rlbridge.wire.seal import SealedCodec

F64 = "std_msgs/msg/Float64"
WAIT = 10.0


def write(issued: Issued, directory: Path, stem: str) -> tuple[Path, Path]:
    cert, key = directory / f"{stem}.crt", directory / f"{stem}.key"
    issued.write(cert, key)
    return cert, key


def wait_until(predicate: Callable[[], object]) -> None:
    deadline = time.monotonic() + WAIT
    while not predicate():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.01)


def counters(srv: ServerThread) -> dict[str, int]:
    assert srv.server.registry is not None
    return dict(srv.server.registry.ctx.counters)


def round_trip(bridge: Bridge, topic: str, n: int = 20) -> list[float]:
    out = bridge.publish(topic, F64, transport="tcp")
    inp = bridge.subscribe(topic, F64, transport="tcp", blocking=True, buffer_size=n)
    for i in range(n):
        out.write(float(i))
    bridge.send(wait=True)
    return [inp.read(timeout=WAIT) for _ in range(n)]


@pytest.fixture
def self_signed(tmp_path: Path) -> tuple[Path, Path, str]:
    return init_server(tmp_path / "tls")


@pytest.fixture
def tls_server(make_server: Callable[..., ServerThread],
               self_signed: tuple[Path, Path, str]) -> ServerThread:
    cert, key, _fp = self_signed
    return make_server(tls_cert=cert, tls_key=key)


def test_pinned_fingerprint_moves_values(tls_server: ServerThread,
                                         self_signed: tuple[Path, Path, str]) -> None:
    fp = self_signed[2]
    pretty = ":".join(fp[i:i + 2] for i in range(0, 64, 2)).upper()  # openssl's way
    with Bridge.connect("127.0.0.1", tls_server.port, security=Tls(fingerprint=pretty),
                        reconnect=False) as bridge:
        assert round_trip(bridge, "/tls/pin") == [float(i) for i in range(20)]
    assert counters(tls_server)["tls_sessions"] == 1


def test_ca_file_and_own_context_are_trusted(tls_server: ServerThread,
                                             self_signed: tuple[Path, Path, str]) -> None:
    cert = self_signed[0]
    with Bridge.connect("127.0.0.1", tls_server.port, security=Tls(ca=cert),
                        reconnect=False) as bridge:
        assert round_trip(bridge, "/tls/ca", 5)[-1] == 4.0
    ctx = ssl.create_default_context(cafile=str(cert))
    with Bridge.connect("localhost", tls_server.port, security=Tls(context=ctx),
                        reconnect=False) as bridge:
        assert bridge.server_stats()["server"]["tls_sessions"] >= 2


def test_refusals_are_one_line_and_leave_the_server_serving(
        tls_server: ServerThread, self_signed: tuple[Path, Path, str], tmp_path: Path) -> None:
    fp = self_signed[2]
    other_ca = make_ca("some other CA")
    other_ca_file = write(other_ca, tmp_path, "other-ca")[0]
    with Bridge.connect("127.0.0.1", tls_server.port, security=Tls(fingerprint=fp),
                        reconnect=False) as good:
        out = good.publish("/tls/alive", F64, transport="tcp")
        inp = good.subscribe("/tls/alive", F64, transport="tcp", blocking=True, buffer_size=8)
        attempts: list[tuple[Tls | None, type[Exception], str]] = [
            (Tls(), TlsFailed, "does not verify: self-signed certificate"),
            (Tls(ca=other_ca_file), TlsFailed, "does not verify"),
            (Tls(fingerprint="ab" * 32), TlsFailed, "not the pinned"),
            (None, AuthRefused, "this server requires TLS"),
        ]
        for security, error, text in attempts:
            with pytest.raises(error, match=text) as info:
                Bridge.connect("127.0.0.1", tls_server.port, reconnect=False, timeout=WAIT,
                               security=security)
            assert "\n" not in str(info.value)
        out.write(1.5)
        good.send(wait=True)
        assert inp.read(timeout=WAIT) == 1.5
    seen = counters(tls_server)
    assert seen["tls_failed"] >= 1  # the CA-checking clients abort with an alert
    assert seen["tls_plaintext_clients"] == 1


def test_tls_client_against_a_plaintext_server(make_server: Callable[..., ServerThread],
                                               self_signed: tuple[Path, Path, str]) -> None:
    plain = make_server()
    with pytest.raises(TlsFailed, match="does not use TLS"):
        Bridge.connect("127.0.0.1", plain.port, security=Tls(fingerprint=self_signed[2]),
                       reconnect=False)
    with Bridge.connect("127.0.0.1", plain.port, reconnect=False) as bridge:
        assert round_trip(bridge, "/plain/after", 3) == [0.0, 1.0, 2.0]


@pytest.mark.parametrize(("shift", "message_ca", "message_pin"), [
    (-30, "certificate has expired", "expired on"),
    (+30, "certificate is not yet valid", "not valid yet"),
])
def test_expired_and_not_yet_valid_certificates(
        make_server: Callable[..., ServerThread], tmp_path: Path, shift: int,
        message_ca: str, message_pin: str) -> None:
    ca = make_ca()
    ca_file = write(ca, tmp_path, "ca")[0]
    now = datetime.datetime.now(datetime.timezone.utc)
    start = now + datetime.timedelta(days=shift)
    leaf = issue("localhost", names=["localhost", "127.0.0.1"], ca=ca, not_before=start,
                 days=10)
    cert, key = write(leaf, tmp_path, "server")
    srv = make_server(tls_cert=cert, tls_key=key)
    with pytest.raises(TlsFailed, match=message_ca):
        Bridge.connect("127.0.0.1", srv.port, security=Tls(ca=ca_file), reconnect=False)
    with pytest.raises(TlsFailed, match=message_pin):
        Bridge.connect("127.0.0.1", srv.port, security=Tls(fingerprint=leaf.fingerprint),
                       reconnect=False)


def test_mutual_tls_names_the_client_and_refuses_others(
        make_server: Callable[..., ServerThread], tmp_path: Path) -> None:
    ca = make_ca()
    ca_file = write(ca, tmp_path, "ca")[0]
    server_cert = issue("localhost", names=["127.0.0.1"], ca=ca)
    cert, key = write(server_cert, tmp_path, "server")
    srv = make_server(tls_cert=cert, tls_key=key, tls_client_ca=ca_file)
    robot_cert, robot_key = write(issue("robot-7", ca=ca, client=True), tmp_path, "robot")
    stranger = write(issue("robot-7", ca=make_ca("rogue"), client=True), tmp_path, "rogue")
    with Bridge.connect("127.0.0.1", srv.port, security=Tls(ca=ca_file, client_cert=(robot_cert,
                                                                                     robot_key)),
                        name="whatever", reconnect=False) as bridge:
        mine = bridge.server_stats()["session"]
        assert mine["identity"] == "robot-7"
        assert mine["name"] == "whatever"
    for client_cert in (None, stranger):
        with pytest.raises(TlsFailed, match="refused the TLS session") as info:
            Bridge.connect("127.0.0.1", srv.port, security=Tls(ca=ca_file,
                                                               client_cert=client_cert),
                           reconnect=False)
        assert "\n" not in str(info.value)
    assert counters(srv)["tls_failed"] == 2


def test_silent_peer_and_garbage_do_not_hang_the_handshake(
        tls_server: ServerThread, self_signed: tuple[Path, Path, str]) -> None:
    """A client that connects and sends nothing, or garbage, costs only its own connection."""
    with socket.create_connection(("127.0.0.1", tls_server.port), timeout=WAIT) as idle, \
            socket.create_connection(("127.0.0.1", tls_server.port), timeout=WAIT) as junk:
        junk.sendall(b"\x16\x03\x01\x00\x05hello" + b"\x00" * 64)
        assert junk.recv(4096) is not None  # an alert, then the close (no hang)
        with Bridge.connect("127.0.0.1", tls_server.port, security=Tls(fingerprint=self_signed[2]),
                            reconnect=False) as bridge:
            assert round_trip(bridge, "/tls/while_idle", 2) == [0.0, 1.0]
        idle.settimeout(0.01)
        with pytest.raises(TimeoutError):
            idle.recv(1)  # still open, waiting for its hello deadline: not our business


def test_unreadable_files_are_one_line_server_errors(
        make_server: Callable[..., ServerThread], tmp_path: Path,
        self_signed: tuple[Path, Path, str]) -> None:
    from rlbridge.server import ServerError

    with pytest.raises(ServerError, match="no such file"):
        make_server(tls_cert=tmp_path / "missing.crt", tls_key=self_signed[1])
    junk = tmp_path / "junk.pem"
    junk.write_text("not a certificate\n")
    with pytest.raises(ServerError, match="cannot use the TLS certificate"):
        make_server(tls_cert=junk, tls_key=self_signed[1])
    with pytest.raises(ValueError, match="not a SHA-256 fingerprint"):
        Bridge.connect("127.0.0.1", 1, security=Tls(fingerprint="abc"), reconnect=False)


def test_udp_channels_of_a_tls_session_are_sealed(tls_server: ServerThread,
                                                  self_signed: tuple[Path, Path, str]) -> None:
    """The datagram keys come over TLS; a datagram without the seal is dropped and counted."""
    with Bridge.connect("127.0.0.1", tls_server.port, security=Tls(fingerprint=self_signed[2]),
                        reconnect=False) as bridge:
        out = bridge.publish("/tls/udp", F64, transport="udp")
        inp = bridge.subscribe("/tls/udp", F64, transport="udp", blocking=True, buffer_size=8)
        out.write(2.5)
        bridge.send(wait=True)
        assert inp.read(timeout=WAIT) == 2.5
        assert tls_server.server.registry is not None
        session = next(iter(tls_server.server.registry))
        assert isinstance(session.codec, SealedCodec)
        token = bridge._conn.ack.token  # type: ignore[union-attr]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            udp.sendto(PacketCodec().encode_datagram(Value(1, 1, 0, 99.0), token),
                       ("127.0.0.1", tls_server.port))
            wait_until(lambda: counters(tls_server).get("udp_unsealed") == 1)
        out.write(3.5)
        bridge.send(wait=True)
        assert inp.read(timeout=WAIT) == 3.5


def test_udp_only_hello_is_refused_by_a_tls_only_server(tls_server: ServerThread) -> None:
    codec = PacketCodec()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.settimeout(WAIT)
        udp.sendto(codec.encode_datagram(Hello(PROTOCOL_VERSION, "udp-only"), 0),
                   ("127.0.0.1", tls_server.port))
        packet = codec.decode_datagram(udp.recv(65536))[2]
    assert isinstance(packet, ConnectError)
    assert "open the session over TCP with TLS" in packet.reason


def test_tls_and_a_key_together(make_server: Callable[..., ServerThread],
                                self_signed: tuple[Path, Path, str], tmp_path: Path) -> None:
    """The key handshake runs inside TLS; its keys seal the datagrams; TCP is not sealed twice."""
    keys = tmp_path / "keys"
    keys.write_text(f"robot {'ab' * 32}\n")
    keys.chmod(0o600)
    cert, key, fp = self_signed
    srv = make_server(tls_cert=cert, tls_key=key, psk_file=keys)
    with pytest.raises(AuthRefused, match="no pre-shared key for client name 'anonymous'"):
        Bridge.connect("127.0.0.1", srv.port, security=Tls(fingerprint=fp), name="anonymous",
                       reconnect=False)
    with Bridge.connect("127.0.0.1", srv.port, security=Tls(fingerprint=fp,
                                                            psk=Psk(key="ab" * 32)), name="robot",
                        reconnect=False) as bridge:
        for transport in ("tcp", "udp"):
            out = bridge.publish(f"/both/{transport}", F64, transport=transport)
            inp = bridge.subscribe(f"/both/{transport}", F64, transport=transport,
                                   blocking=True)
            out.write(7.0)
            bridge.send(wait=True)
            assert inp.read(timeout=WAIT) == 7.0
        assert bridge.server_stats()["session"]["identity"] == "robot"
    seen = counters(srv)
    assert seen["sessions_authenticated"] == 1
    assert "tcp_rejected_records" not in seen


@pytest.mark.parametrize("mode", ["tls", "psk"])
def test_a_protected_session_reconnects_with_fresh_keys(
        tmp_path: Path, self_signed: tuple[Path, Path, str], mode: str) -> None:
    """After a server restart the SDK runs the TLS or key handshake again by itself."""
    from rlbridge.server import ServerConfig

    cert, key, fp = self_signed
    keys = tmp_path / "keys"
    keys.write_text("ab" * 32 + "\n")
    keys.chmod(0o600)
    extra: dict[str, object] = ({"tls_cert": cert, "tls_key": key} if mode == "tls"
                                else {"psk_file": keys})
    client = Tls(fingerprint=fp) if mode == "tls" else Psk(key="ab" * 32)
    config = ServerConfig(port=0, heartbeat_ms=50, timeout_ms=1000, **extra)  # type: ignore[arg-type]
    first = ServerThread(config).start()
    port = first.port
    bridge = Bridge.connect("127.0.0.1", port, timeout=WAIT, security=client)
    try:
        out = bridge.publish("/again/x", F64, transport="tcp")
        inp = bridge.subscribe("/again/x", F64, transport="udp", blocking=True, buffer_size=64)
        first.stop()
        second = ServerThread(config.model_copy(update={"port": port})).start()
        try:
            wait_until(lambda: bridge.reconnects >= 1 and bridge.state == "connected")
            deadline = time.monotonic() + WAIT
            got = None
            while got != 9.0:  # values flow again over the new session's TCP and UDP
                assert time.monotonic() < deadline, "no value after the reconnect"
                out.write(9.0)
                bridge.send(wait=True)
                try:
                    got = inp.read(timeout=0.2)
                except TimeoutError:
                    continue
        finally:
            bridge.close()
            second.stop()
    finally:
        bridge.close()
