"""A pre-shared-key session's TCP stream: sealed records, and what happens to injected bytes.

Sans-IO first (the record layer in any chunking, every way a record can be wrong), then live:
a raw client that injects a frame into its own sealed stream, and an on-path relay between the
SDK and the server that reads the stream (it must see no plaintext) and injects a frame into it
(the session must end with a clear reason, and other sessions go on).
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from rlbridge import ErrorCode, Psk, RemoteProtocolError
from rlbridge.csp.auth import ClientAuth
from rlbridge.csp.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.wire import (
    PROTOCOL_VERSION,
    AuthChallenge,
    AuthProof,
    ConnectAck,
    Disconnect,
    Error,
    FrameDecoder,
    Heartbeat,
    Hello,
    PacketCodec,
    Stats,
    TopicAck,
    TopicConnect,
    Value,
)
from rlbridge.wire.aead import BULK_FROM, CRYPTOGRAPHY, IMPLEMENTATIONS
from rlbridge.wire.records import (
    RECORD_MAX,
    RecordOpener,
    RecordSealer,
    SealedStreamDecoder,
    stream_sealers,
)
from rlbridge.wire.seal import derive_keys, nonce

F64 = "std_msgs/msg/Float64"
KEY = bytes(range(32))
WAIT = 10.0
CODEC = PacketCodec()


def keys_pair() -> tuple[RecordSealer, SealedStreamDecoder]:
    keys = derive_keys(KEY, b"salt", b"context")
    sealer, _ = stream_sealers(keys, server=False)
    _, opener_key = stream_sealers(keys, server=True)
    decoder = SealedStreamDecoder(CODEC)
    decoder.install(RecordOpener(opener_key), strict=True)
    return sealer, decoder


def frames(n: int) -> bytes:
    return b"".join(CODEC.encode_frame(Value(1, i, i, float(i))) for i in range(n))


# -- sans-IO --------------------------------------------------------------------------------


@pytest.mark.parametrize("chunk", [1, 7, 100, 1 << 20])
def test_records_round_trip_in_any_chunking(chunk: int) -> None:
    sealer, decoder = keys_pair()
    wire = sealer.seal(frames(50)) + sealer.seal(frames(3))
    got = []
    for i in range(0, len(wire), chunk):
        got += decoder.feed(wire[i:i + chunk])
    assert got == [Value(1, i, i, float(i)) for i in range(50)] + [
        Value(1, i, i, float(i)) for i in range(3)]


def test_a_frame_larger_than_a_record_spans_records() -> None:
    sealer, decoder = keys_pair()
    big = Value(1, 0, 0, "x" * (RECORD_MAX * 2))
    assert decoder.feed(sealer.seal(CODEC.encode_frame(big))) == [big]


@pytest.mark.parametrize("size", [1, BULK_FROM - 1, BULK_FROM, 3 * BULK_FROM, RECORD_MAX + 5])
def test_small_and_bulk_records_are_the_same_construction(size: int) -> None:
    """A record of BULK_FROM bytes or more is sealed and opened by cryptography's
    ChaCha20-Poly1305, a smaller one by the install's choice: the bytes of each record are
    those of the one construction (docs/protocol.md section 16.5), whichever sealed it."""
    sealer, decoder = keys_pair()
    data = bytes(range(256)) * (size // 256 + 1)
    frame = CODEC.encode_frame(Value(1, 0, 0, data[:size]))
    wire = sealer.seal(frame)
    key = derive_keys(KEY, b"salt", b"context").stream_client_to_server
    reference, at, counter = IMPLEMENTATIONS[CRYPTOGRAPHY](key), 0, 0
    for start in range(0, len(frame), RECORD_MAX):  # each record, sealed by one reference
        chunk = frame[start:start + RECORD_MAX]
        record = wire[at:at + 8 + len(chunk) + 16]
        assert record == record[:8] + reference.encrypt(nonce(counter), chunk, record[:8])
        at, counter = at + len(record), counter + 1
    assert at == len(wire)
    assert decoder.feed(wire) == [Value(1, 0, 0, data[:size])]


@pytest.mark.parametrize("attack", ["flip", "replay", "reorder", "drop", "plain", "reflect"])
def test_every_tampering_ends_the_stream(attack: str) -> None:
    sealer, decoder = keys_pair()
    one, two = sealer.seal(frames(1)), sealer.seal(frames(2))
    stream = {
        "flip": one[:-3] + bytes([one[-3] ^ 1]) + one[-2:],
        "replay": one + one,
        "reorder": two + one,
        "drop": two,
        "plain": one + frames(1),
        "reflect": stream_sealers(derive_keys(KEY, b"salt", b"context"),
                                  server=True)[0].seal(frames(1)),
    }[attack]
    with pytest.raises(RemoteProtocolError) as exc:
        decoder.feed(stream)
    assert exc.value.fatal
    assert exc.value.code == ErrorCode.AUTH_FAILED
    with pytest.raises(RemoteProtocolError):  # broken for good
        decoder.feed(b"")


def test_records_wait_for_the_key_and_the_client_accepts_a_plain_refusal() -> None:
    keys = derive_keys(KEY, b"salt", b"context")
    server_sealer, _ = stream_sealers(keys, server=True)
    _, client_key = stream_sealers(keys, server=False)
    decoder = SealedStreamDecoder(CODEC)
    plain = CODEC.encode_frame(Heartbeat(1))
    assert decoder.feed(plain + server_sealer.seal(frames(1))) == [Heartbeat(1)]
    assert decoder.buffered > 0  # the record waits for the key
    decoder.install(RecordOpener(client_key), strict=False)
    assert decoder.feed(b"") == [Value(1, 0, 0, 0.0)]
    with pytest.raises(RemoteProtocolError, match="unsealed frame"):
        decoder.feed(plain)  # after the first record, plain frames are refused


def test_decoding_stops_after_the_proof_until_the_key_is_there() -> None:
    """Whatever follows the AuthProof in the same read is never taken as plain."""
    keys = derive_keys(KEY, b"salt", b"context")
    _, server_key = stream_sealers(keys, server=True)
    decoder = SealedStreamDecoder(CODEC, stop_after=AuthProof)
    injected = CODEC.encode_frame(Value(1, 0, 0, 6.0))
    got = decoder.feed(CODEC.encode_frame(AuthProof(bytes(32))) + injected)
    assert got == [AuthProof(bytes(32))]
    decoder.install(RecordOpener(server_key), strict=True)
    with pytest.raises(RemoteProtocolError, match="unsealed frame"):
        decoder.feed(b"")


def test_records_before_the_key_are_bounded() -> None:
    sealer = RecordSealer(bytes(32))
    decoder = SealedStreamDecoder(CODEC)
    decoder.feed(sealer.seal(b"x" * RECORD_MAX))  # one record may wait for its key
    with pytest.raises(RemoteProtocolError, match="before the handshake"):
        decoder.feed(sealer.seal(b"x" * 100))


def test_oversized_record_and_frame_are_refused_from_the_header() -> None:
    _, decoder = keys_pair()
    from rlbridge.wire import FRAME_HEADER, MAGIC

    head = FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 1, RECORD_MAX + 17)
    with pytest.raises(RemoteProtocolError, match="exceeds") as exc:
        decoder.feed(head)
    assert exc.value.code == ErrorCode.TOO_LARGE
    fresh = SealedStreamDecoder(CODEC, max_packet=1024)
    with pytest.raises(RemoteProtocolError, match="exceeds"):
        fresh.feed(FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, 4096))


# -- live -----------------------------------------------------------------------------------


@pytest.fixture
def psk_server(make_server: Callable[..., ServerThread], tmp_path: Path) -> ServerThread:
    path = tmp_path / "keys"
    path.write_text(KEY.hex() + "\n")
    path.chmod(0o600)
    return make_server(psk_file=path)


def counters(srv: ServerThread) -> dict[str, int]:
    assert srv.server.registry is not None
    return dict(srv.server.registry.ctx.counters)


def raw_sealed_session(port: int) -> tuple[socket.socket, RecordSealer, SealedStreamDecoder]:
    """A raw client through the key handshake: its socket, record sealer and decoder."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=WAIT)
    auth = ClientAuth(KEY, "raw")
    sock.sendall(CODEC.encode_frame(Hello(PROTOCOL_VERSION, "raw", auth.nonce)))
    challenge = FrameDecoder(CODEC).feed(sock.recv(65536))[0]
    assert isinstance(challenge, AuthChallenge)
    sock.sendall(CODEC.encode_frame(auth.answer(challenge, sock)))
    assert auth.keys is not None
    sealer, opener_key = stream_sealers(auth.keys, server=False)
    decoder = SealedStreamDecoder(CODEC)
    decoder.install(RecordOpener(opener_key), strict=False)
    got: list[object] = []
    while not got:
        got = list(decoder.feed(sock.recv(65536)))
    assert isinstance(got[0], ConnectAck)
    return sock, sealer, decoder


def read_until_closed(sock: socket.socket, decoder: SealedStreamDecoder) -> list[object]:
    packets: list[object] = []
    while data := sock.recv(65536):
        packets += decoder.feed(data)
    return packets


def test_a_frame_injected_into_a_sealed_stream_ends_the_session(psk_server: ServerThread
                                                                ) -> None:
    with Bridge.connect("127.0.0.1", psk_server.port, security=Psk(key=KEY),
                        reconnect=False) as bystander:
        out = bystander.publish("/sealed/alive", F64, transport="tcp")
        inp = bystander.subscribe("/sealed/alive", F64, transport="tcp", blocking=True)
        sock, sealer, decoder = raw_sealed_session(psk_server.port)
        with sock:
            sock.sendall(sealer.seal(CODEC.encode_frame(Stats())))  # a genuine record: fine
            answer: list[object] = []
            while not any(isinstance(p, Stats) for p in answer):
                answer += decoder.feed(sock.recv(65536))
            sock.sendall(CODEC.encode_frame(Value(1, 0, 0, 6.0)))  # injected in plain
            packets = read_until_closed(sock, decoder)
        errors = [p for p in packets if isinstance(p, Error)]
        assert errors
        assert errors[0].code == ErrorCode.AUTH_FAILED
        assert "unsealed frame" in errors[0].reason
        assert isinstance(packets[-1], Disconnect)
        out.write(4.0)
        bystander.send(wait=True)
        assert inp.read(timeout=WAIT) == 4.0
    assert counters(psk_server)["tcp_rejected_records"] == 1


def test_a_frame_sent_with_the_proof_is_refused_not_run(psk_server: ServerThread) -> None:
    """An attacker appending a plain frame to the client's proof gets nothing bound."""
    sock = socket.create_connection(("127.0.0.1", psk_server.port), timeout=WAIT)
    with sock:
        auth = ClientAuth(KEY, "raw")
        sock.sendall(CODEC.encode_frame(Hello(PROTOCOL_VERSION, "raw", auth.nonce)))
        challenge = FrameDecoder(CODEC).feed(sock.recv(65536))[0]
        assert isinstance(challenge, AuthChallenge)
        proof = auth.answer(challenge, sock)
        injected = CODEC.encode_frame(TopicConnect(1, "publish", "/injected", F64))
        sock.sendall(CODEC.encode_frame(proof) + injected)
        assert auth.keys is not None
        _, opener_key = stream_sealers(auth.keys, server=False)
        decoder = SealedStreamDecoder(CODEC)
        decoder.install(RecordOpener(opener_key), strict=False)
        packets = read_until_closed(sock, decoder)
    assert isinstance(packets[0], ConnectAck)
    assert not any(isinstance(p, TopicAck) for p in packets)
    errors = [p for p in packets if isinstance(p, Error)]
    assert errors
    assert "unsealed frame" in errors[0].reason
    assert psk_server.server.registry is not None
    assert "/injected" not in [t for t, _ in psk_server.server.registry.ctx.adapter.topics()]


class Relay:
    """An on-path attacker as a TCP relay: forwards both ways, records what it sees, and can
    slip bytes into the server-to-client direction."""

    def __init__(self, port: int) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.upstream_port = port
        self.seen_c2s = bytearray()
        self.inject_s2c: bytes | None = None
        self._threads: list[threading.Thread] = []
        self._socks: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        with contextlib.suppress(OSError):
            client, _ = self.listener.accept()
            server = socket.create_connection(("127.0.0.1", self.upstream_port))
            self._socks += [client, server]
            for src, dst, c2s in ((client, server, True), (server, client, False)):
                t = threading.Thread(target=self._pump, args=(src, dst, c2s), daemon=True)
                t.start()
                self._threads.append(t)

    def _pump(self, src: socket.socket, dst: socket.socket, c2s: bool) -> None:
        with contextlib.suppress(OSError):
            while data := src.recv(65536):
                if c2s:
                    self.seen_c2s += data
                elif self.inject_s2c is not None:
                    data, self.inject_s2c = self.inject_s2c + data, None
                dst.sendall(data)
        with contextlib.suppress(OSError):
            dst.shutdown(socket.SHUT_WR)

    def close(self) -> None:
        self.listener.close()
        for sock in self._socks:
            sock.close()
        for t in self._threads:
            t.join(WAIT)


def test_on_path_relay_sees_no_plaintext_and_its_injection_ends_the_session(
        psk_server: ServerThread) -> None:
    relay = Relay(psk_server.port)
    try:
        bridge = Bridge.connect("127.0.0.1", relay.port, security=Psk(key=KEY), reconnect=False,
                                name="via-relay")
        with bridge:
            out = bridge.publish("/secret_setpoint", F64, transport="tcp")
            out.write(12345.5)
            bridge.send(wait=True)
            assert b"/secret_setpoint" not in relay.seen_c2s
            assert b"via-relay" in relay.seen_c2s  # the hello is plain (docs/security.md)
            relay.inject_s2c = CODEC.encode_frame(Value(1, 99, 0, -1.0))
            deadline = time.monotonic() + WAIT
            while not bridge.closed:  # the next heartbeat from the server carries it in
                assert time.monotonic() < deadline, "session did not end"
                time.sleep(0.01)
            assert "unsealed frame" in bridge.close_reason
    finally:
        relay.close()
