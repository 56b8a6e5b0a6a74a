"""The edges of docs/protocol.md sections 2, 12.2 and 16, each sent by a raw socket.

Every case the document settles is sent as bytes by a client that does not use the SDK: what
the server answers (code and packet, sealed or plain) and which counter it feeds. The TCP
cases of a keyed session run after a real key handshake (the record layer is live).
"""

from __future__ import annotations

import socket
import struct
from collections.abc import Callable
from pathlib import Path

import pytest

from rlbridge.adapters.base import QoS
from rlbridge.adapters.inproc import InProcessBus
from rlbridge.client.session.auth import ClientAuth
from rlbridge.server import ServerThread
from rlbridge.wire import (
    FRAME_HEADER,
    MAGIC,
    PROTOCOL_VERSION,
    AuthChallenge,
    AuthProof,
    ConnectAck,
    ConnectError,
    Disconnect,
    Error,
    ErrorCode,
    FrameDecoder,
    Heartbeat,
    Hello,
    PacketCodec,
    Stats,
    TopicAck,
    TopicConnect,
    Value,
)
from rlbridge.wire.aead import chacha20_poly1305
from rlbridge.wire.records import RECORD_MAX, RecordOpener, SealedStreamDecoder, stream_sealers
from rlbridge.wire.seal import SessionKeys, sealed_codec

KEY = bytes(range(32))
WAIT = 10.0
CODEC = PacketCodec()
SEALED = 0x01
#: The largest length field of a record: 65 536 bytes of frames and the 16-byte tag.
RECORD_LIMIT = RECORD_MAX + 16
F64 = "std_msgs/msg/Float64"


@pytest.fixture
def psk_server(make_server: Callable[..., ServerThread], tmp_path: Path) -> ServerThread:
    path = tmp_path / "keys"
    path.write_text(KEY.hex() + "\n")
    path.chmod(0o600)
    return make_server(psk_file=path)


def counters(srv: ServerThread) -> dict[str, int]:
    assert srv.server.registry is not None
    return dict(srv.server.registry.ctx.counters)


class SealedClient:
    """A raw client through the key handshake over TCP: its socket, keys and record layer."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=WAIT)
        auth = ClientAuth(KEY, "raw")
        self.sock.sendall(CODEC.encode_frame(Hello(PROTOCOL_VERSION, "raw", auth.nonce)))
        challenge = FrameDecoder(CODEC).feed(self.sock.recv(65536))[0]
        assert isinstance(challenge, AuthChallenge)
        self.sock.sendall(CODEC.encode_frame(auth.answer(challenge, self.sock)))
        assert auth.keys is not None
        self.keys: SessionKeys = auth.keys
        self.sealer, opener_key = stream_sealers(auth.keys, server=False)
        self.decoder = SealedStreamDecoder(CODEC)
        self.decoder.install(RecordOpener(opener_key), strict=False)
        got: list[object] = []
        while not got:
            got = list(self.decoder.feed(self.sock.recv(65536)))
        assert isinstance(got[0], ConnectAck)
        self.ack = got[0]

    def until_closed(self) -> list[object]:
        """Every packet the server sends until it closes (each one opened as a record: an
        unsealed one would fail here)."""
        packets: list[object] = []
        while data := self.sock.recv(65536):
            packets += [p for p in self.decoder.feed(data) if not isinstance(p, Heartbeat)]
        self.sock.close()
        return packets


def ends_with(packets: list[object], code: ErrorCode, reason: str) -> None:
    """``Error(code)`` with ``reason`` in it, then ``Disconnect(code)``, then nothing."""
    assert len(packets) >= 2, packets
    error, goodbye = packets[-2:]
    assert isinstance(error, Error), packets
    assert (error.code, reason in error.reason) == (code, True), error
    assert isinstance(goodbye, Disconnect), packets
    assert goodbye.code == code


def plain_answer(sock: socket.socket) -> list[object]:
    """The plain frames a server sends before it closes the connection."""
    decoder, packets = FrameDecoder(CODEC), []
    while data := sock.recv(65536):
        packets += decoder.feed(data)
    sock.close()
    return packets


# -- 16.5: the record layer of a keyed session ---------------------------------------------


@pytest.mark.parametrize("length", [RECORD_LIMIT + 1, 1_500_000_000])
def test_an_oversized_record_is_refused_from_its_header_as_injected(
        psk_server: ServerThread, length: int) -> None:
    """A length field over 65 552 (one byte over; a header announcing 1.5 GB): Error(21) and
    Disconnect(21), both sealed, counted as a rejected record; the body is never awaited."""
    client = SealedClient(psk_server.port)
    client.sock.sendall(FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, SEALED, length))
    ends_with(client.until_closed(), ErrorCode.AUTH_FAILED, f"record of {length} bytes")
    got = counters(psk_server)
    assert (got.get("tcp_rejected_records"), got.get("malformed", 0)) == (1, 0)


def test_a_record_of_the_largest_length_is_taken(psk_server: ServerThread) -> None:
    """The limit is the length field: 65 536 bytes of frames and the tag (65 560 on the wire
    with the header) is one record; the frames in it run."""
    client = SealedClient(psk_server.port)
    stream = CODEC.encode_frame(Heartbeat(1)) * (RECORD_MAX // 15) + CODEC.encode_frame(Stats())
    wire = client.sealer.seal(stream)
    assert struct.unpack_from(">I", wire, 4)[0] == RECORD_LIMIT
    client.sock.sendall(wire)
    got: list[object] = []
    while not any(isinstance(p, Stats) for p in got):
        got += client.decoder.feed(client.sock.recv(65536))
    client.sock.close()
    assert counters(psk_server).get("tcp_rejected_records", 0) == 0


@pytest.mark.parametrize("header", [
    FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, 2),  # a plain frame (injected)
    FRAME_HEADER.pack(b"XX", PROTOCOL_VERSION, SEALED, 32),  # not our magic
    FRAME_HEADER.pack(MAGIC, 2, SEALED, 32),  # another version
], ids=["plain", "magic", "version"])
def test_anything_but_a_record_after_the_handshake_is_refused_as_injected(
        psk_server: ServerThread, header: bytes) -> None:
    client = SealedClient(psk_server.port)
    client.sock.sendall(header + b"\x91\x0a")
    ends_with(client.until_closed(), ErrorCode.AUTH_FAILED, "injected on the way?")
    got = counters(psk_server)
    assert (got.get("tcp_rejected_records"), got.get("malformed", 0)) == (1, 0)


def test_a_frame_with_bit_0_inside_a_record_is_malformed(psk_server: ServerThread) -> None:
    """Records do not nest: a frame header inside a record with SEALED set loses the
    framing, from a peer that holds the key: Error(2) and Disconnect(2), sealed, counted
    as malformed (not as a rejected record)."""
    client = SealedClient(psk_server.port)
    frame = bytearray(CODEC.encode_frame(Heartbeat(1)))
    frame[3] = SEALED
    client.sock.sendall(client.sealer.seal(bytes(frame)))
    ends_with(client.until_closed(), ErrorCode.MALFORMED, "flags bit 0")
    got = counters(psk_server)
    assert (got.get("malformed"), got.get("tcp_rejected_records", 0)) == (1, 0)


def test_a_record_cut_short_by_the_end_of_the_stream_closes_quietly(
        psk_server: ServerThread) -> None:
    """The stream ends inside a record: a lost connection, answered with nothing (the peer
    stopped sending) and counted nowhere (a peer that dies mid-write looks the same)."""
    client = SealedClient(psk_server.port)
    record = client.sealer.seal(CODEC.encode_frame(Stats()))
    client.sock.sendall(record[:len(record) // 2])
    client.sock.shutdown(socket.SHUT_WR)
    assert client.until_closed() == []
    got = counters(psk_server)
    assert (got.get("tcp_rejected_records", 0), got.get("malformed", 0)) == (0, 0)


def publishing_client(srv: ServerThread, topic: str) -> tuple[SealedClient, list[object]]:
    """A sealed client with channel 1 bound to publish on ``topic``, and every value the
    server's in-process bus delivers there (synchronously, on the server's loop)."""
    registry = srv.server.registry
    assert registry is not None
    bus = registry.ctx.adapter
    assert isinstance(bus, InProcessBus)
    published: list[object] = []
    bus.subscribe(topic, F64, "data", QoS(), published.extend)
    client = SealedClient(srv.port)
    client.sock.sendall(client.sealer.seal(CODEC.encode_frame(
        TopicConnect(1, "publish", topic, F64, transport="tcp"))))
    got: list[object] = []
    while not any(isinstance(p, TopicAck) for p in got):  # bounded by the socket's timeout
        got += client.decoder.feed(client.sock.recv(65536))
    return client, published


@pytest.mark.parametrize(("case", "code", "reason", "counter"), [
    ("injected-frame", ErrorCode.AUTH_FAILED, "unsealed frame", "tcp_rejected_records"),
    ("bad-frame-in-record", ErrorCode.MALFORMED, "bad magic b'XX'", "malformed"),
])
def test_records_before_a_bad_one_in_the_same_write_run_first(
        psk_server: ServerThread, case: str, code: ErrorCode, reason: str,
        counter: str) -> None:
    """Records of values, then a plain frame injected after them, or a record whose last
    frame has a bad header, all in one write: every value before the fault is published,
    then the stream is refused as it would be alone."""
    client, published = publishing_client(psk_server, "/sealed/run")
    seal = client.sealer.seal
    values = [CODEC.encode_frame(Value(1, i, 0, float(i))) for i in range(4)]
    stream = seal(b"".join(values[:2])) + seal(values[2])  # sealed in order: the counter
    if case == "injected-frame":
        stream += seal(values[3]) + FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, 2) + b"\x91\x0a"
    else:
        stream += seal(values[3] + FRAME_HEADER.pack(b"XX", PROTOCOL_VERSION, 0, 2))
    client.sock.sendall(stream)
    ends_with(client.until_closed(), code, reason)
    assert published == [0.0, 1.0, 2.0, 3.0]
    assert counters(psk_server).get(counter) == 1


def test_a_hello_and_a_bad_header_in_one_write_get_the_challenge_then_the_refusal(
        psk_server: ServerThread) -> None:
    """The hello before the bad header is answered (AuthChallenge) before the stream is
    refused (ConnectError(2), plain: no session exists), as if each had come alone."""
    sock = socket.create_connection(("127.0.0.1", psk_server.port), timeout=WAIT)
    auth = ClientAuth(KEY, "raw")
    sock.sendall(CODEC.encode_frame(Hello(PROTOCOL_VERSION, "raw", auth.nonce))
                 + FRAME_HEADER.pack(b"XX", PROTOCOL_VERSION, 0, 2))
    answer = plain_answer(sock)
    assert [type(p) for p in answer] == [AuthChallenge, ConnectError]
    assert isinstance(answer[1], ConnectError)
    assert (answer[1].code, "bad magic" in answer[1].reason) == (ErrorCode.MALFORMED, True)


# -- section 2: flags bit 0 where no record can be --------------------------------------------


def test_a_first_frame_with_bit_0_is_refused_at_once_by_a_keyed_server(
        psk_server: ServerThread) -> None:
    """Before the key handshake nothing is sealed: ConnectError(2 MALFORMED), plain, at once
    (not the 10 s hello deadline's ConnectError(4))."""
    sock = socket.create_connection(("127.0.0.1", psk_server.port), timeout=WAIT)
    hello = bytearray(CODEC.encode_frame(Hello(PROTOCOL_VERSION, "raw", bytes(16))))
    hello[3] = SEALED
    sock.sendall(hello)
    answer = plain_answer(sock)
    assert [type(p) for p in answer] == [ConnectError]
    assert isinstance(answer[0], ConnectError)
    assert (answer[0].code, "before the key" in answer[0].reason) == (ErrorCode.MALFORMED, True)


def test_a_record_sent_with_the_hello_before_the_proof_is_refused(
        psk_server: ServerThread) -> None:
    """A sealed record between Hello and AuthProof: no key exists yet."""
    sock = socket.create_connection(("127.0.0.1", psk_server.port), timeout=WAIT)
    auth = ClientAuth(KEY, "raw")
    sock.sendall(CODEC.encode_frame(Hello(PROTOCOL_VERSION, "raw", auth.nonce)))
    decoder = FrameDecoder(CODEC)
    assert isinstance(decoder.feed(sock.recv(65536))[0], AuthChallenge)
    sock.sendall(FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, SEALED, 40) + bytes(40)
                 + CODEC.encode_frame(AuthProof(bytes(32))))
    answer = plain_answer(sock)
    assert [type(p) for p in answer] == [ConnectError]
    assert isinstance(answer[0], ConnectError)
    assert (answer[0].code, "before the key" in answer[0].reason) == (ErrorCode.MALFORMED, True)


def test_a_first_frame_with_bit_0_is_refused_by_a_server_without_keys(
        server: ServerThread) -> None:
    sock = socket.create_connection(("127.0.0.1", server.port), timeout=WAIT)
    hello = bytearray(CODEC.encode_frame(Hello(PROTOCOL_VERSION, "raw")))
    hello[3] = SEALED
    sock.sendall(hello)
    answer = plain_answer(sock)
    assert [type(p) for p in answer] == [ConnectError]
    assert isinstance(answer[0], ConnectError)
    assert answer[0].code == ErrorCode.MALFORMED


def test_a_frame_with_bit_0_in_a_session_without_keys_ends_it(server: ServerThread) -> None:
    sock = socket.create_connection(("127.0.0.1", server.port), timeout=WAIT)
    sock.sendall(CODEC.encode_frame(Hello(PROTOCOL_VERSION, "raw")))
    assert isinstance(FrameDecoder(CODEC).feed(sock.recv(65536))[0], ConnectAck)
    frame = bytearray(CODEC.encode_frame(Stats()))
    frame[3] = SEALED
    sock.sendall(bytes(frame))
    ends_with([p for p in plain_answer(sock) if not isinstance(p, Heartbeat)],
              ErrorCode.MALFORMED, "flags bit 0")
    assert counters(server).get("malformed") == 1


# -- 16.3: which check of a sealed datagram feeds which counter -------------------------------


def _datagram(keys: SessionKeys, token: int, counter: int, body: bytes,
              flags: int = SEALED) -> bytes:
    head = struct.pack(">2sBBQQ", MAGIC, PROTOCOL_VERSION, flags, token, counter)
    return chacha20_poly1305(keys.client_to_server).seal_counted(counter, head, body)


@pytest.mark.parametrize(("case", "counter"), [
    ("unsealed", "udp_unsealed"),  # no SEALED flag
    ("truncated", "udp_bad_mac"),  # flag set, 35 bytes: the seal cannot open
    ("forged", "udp_bad_mac"),  # a tag that does not verify
    ("zero", "udp_replayed"),  # opens, but counter 0 is never valid
    ("repeated", "udp_replayed"),  # opens, counter seen before
])
def test_each_check_of_a_sealed_datagram_feeds_its_counter(
        psk_server: ServerThread, case: str, counter: str) -> None:
    client = SealedClient(psk_server.port)
    token = client.ack.token
    body = CODEC.encode_frame(Heartbeat(1))[8:]
    good = _datagram(client.keys, token, 1, body)
    datagram = {
        "unsealed": CODEC.encode_datagram(Heartbeat(1), token),
        "truncated": good[:35],
        "forged": good[:-1] + bytes([good[-1] ^ 1]),
        "zero": _datagram(client.keys, token, 0, body),
        "repeated": good,
    }[case]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.connect(("127.0.0.1", psk_server.port))
        if case == "repeated":
            udp.send(good)
        udp.send(datagram)
        # A sealed Stats request with a later counter: its answer means the server has read
        # the datagrams before it (one socket, read in order).
        udp.send(_datagram(client.keys, token, 2, CODEC.encode_frame(Stats())[8:]))
        opener = sealed_codec(client.keys, server=False)
        udp.settimeout(WAIT)
        while not isinstance(opener.decode_datagram(udp.recv(65536))[2], Stats):
            pass
    client.sock.close()
    assert counters(psk_server).get(counter) == 1, counters(psk_server)
