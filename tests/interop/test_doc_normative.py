"""docs/protocol.md is normative: the places an independent implementer found unclear or
contradictory, each checked against a live server with the independent client (nothing from
``rlbridge.wire``; ``rlbridge.server`` only starts the server)."""

from __future__ import annotations

import hashlib
import hmac
import os
import re
import socket
import struct
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import independent_client as ic
import pytest
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305

from rlbridge.server import ServerThread

DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"
HOST = "127.0.0.1"
F64 = "std_msgs/msg/Float64"


@pytest.fixture
def server(make_server: Callable[..., ServerThread]) -> ServerThread:
    return make_server(heartbeat_ms=50, timeout_ms=5000, max_packet=2000)


@pytest.fixture
def session(server: ServerThread) -> Iterator[ic.IndependentClient]:
    with ic.IndependentClient(HOST, server.port, timeout=5) as c:
        c.connect_tcp("normative")
        c.stats(via="udp")  # our UDP address is registered (doc 8.3)
        yield c


def carried_by() -> dict[int, str]:
    """Doc 12.2: code -> its "Carried by" cell."""
    text = DOC.read_text()
    table = text[text.index("### 12.2 Error codes") : text.index("## 13. Limits")]
    rows = re.finditer(r"^\| (\d+)\s+\| [^|]+\| ([^|]+) \|", table, re.M)
    return {int(m[1]): m[2] for m in rows}


def assert_carried(packet: ic.Packet, code: int) -> None:
    assert f"`{packet.name}`" in carried_by()[code], (packet.name, code)


def test_first_heartbeat_comes_before_the_answer_to_a_pipelined_request(
        server: ServerThread) -> None:
    """Doc 8.1 step 3, 11, 15.8: ConnectAck, then at once the heartbeat, then the rest."""
    topic = "/normative/pipelined"
    with socket.create_connection((HOST, server.port), timeout=5) as tcp:
        tcp.sendall(ic.frame(ic.hello("pipelined")) + ic.frame(
            ic.topic_connect(1, "subscribe", topic, F64)) + ic.frame([ic.TAG_STATS]))
        reader = ic.FrameReader()
        tags: list[int] = []
        while ic.TAG_STATS not in tags:
            tags += [body[0] for body in reader.feed(tcp.recv(65536))]
    assert tags[:4] == [ic.TAG_CONNECT_ACK, ic.TAG_HEARTBEAT, ic.TAG_TOPIC_ACK, ic.TAG_STATS]


def test_minimal_topic_connect_of_section_14_3() -> None:
    """Doc 14.3: the minimal body's header byte says 5 elements, and it is what we encode."""
    quoted = re.search(r"The equivalent minimal body is `([0-9a-f ]+) \.\.\.", DOC.read_text())
    assert quoted is not None
    prefix = bytes.fromhex(quoted[1])
    assert ic.packb([ic.TAG_TOPIC_CONNECT, 1, "publish", "/x", F64]).startswith(prefix)
    assert prefix[0] == 0x90 | 5


def test_udp_body_limit_is_max_packet_unsealed_too(session: ic.IndependentClient) -> None:
    """Doc 3 step 3: a body of exactly max_packet passes; one byte more is dropped, also
    when the datagram would fit max_packet plus a seal's 24 bytes."""
    assert session.ack is not None
    assert session.udp is not None
    limit = session.ack.max_packet
    overhead = len(ic.packb([ic.TAG_STATS, {"pad": "x" * 300}])) - 300
    exact = ic.packb([ic.TAG_STATS, {"pad": "x" * (limit - overhead)}])
    assert len(exact) == limit
    header = ic.DATAGRAM_HEADER.pack(b"RB", 1, 0, session.token)
    for extra in (1, 24):
        session.udp.send(header + ic.packb([ic.TAG_STATS, {"pad": "x" * (
            limit - overhead + extra)}]))
    session.udp.send(header + exact)
    body = session.recv_tag(ic.TAG_STATS, via="udp").field(1)
    assert body["server"]["udp_too_large"] == 2
    assert [p for p in session.backlog if p.tag == ic.TAG_STATS] == []  # no answer to those


def test_udp_checks_in_their_documented_order(session: ic.IndependentClient) -> None:
    """Doc 3: header before size, size before token, token before body; only a bad body
    under a live token is answered."""
    assert session.udp is not None
    udp = session.udp
    big = "x" * 2500  # over this server's max_packet of 2000
    unknown = session.token ^ 1
    udp.send(b"XY\x01\x00" + bytes(8) + ic.packb([ic.TAG_STATS, {"p": big}]))  # header first
    udp.send(ic.datagram([ic.TAG_STATS, {"p": big}], unknown))  # size before token
    udp.send(ic.DATAGRAM_HEADER.pack(b"RB", 1, 0, unknown) + b"\xc1")  # token before body
    udp.send(ic.DATAGRAM_HEADER.pack(b"RB", 1, 0, 0) + b"\xc1")  # token 0, bad body: silent
    before = session.stats(via="udp")["server"]  # after those: same socket, in order
    udp.send(ic.DATAGRAM_HEADER.pack(b"RB", 1, 0, session.token) + b"\xc1")  # live: answered
    err = session.recv_tag(ic.TAG_ERROR, via="udp")
    assert err.field(1) == ic.MALFORMED
    assert_carried(err, ic.MALFORMED)
    after = session.stats(via="udp")["server"]
    assert after["udp_malformed"] == before["udp_malformed"] + 1
    assert (before["udp_malformed"], before["udp_too_large"], before["udp_bad_token"]) == (
        2, 1, 1)
    assert [p for p in session.backlog if p.via == "udp"] == []


def test_udp_replies_come_from_the_port_the_client_sent_to(server: ServerThread) -> None:
    """Doc 3, source of replies: an unconnected socket sees the server's own address."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.settimeout(5)
        udp.sendto(ic.datagram(ic.hello("unconnected"), 0), (HOST, server.port))
        data, source = udp.recvfrom(65536)
        assert source == (HOST, server.port)
        flags, token, body = ic.parse_datagram(data)
        assert body[0] == ic.TAG_CONNECT_ACK
        assert (flags, token) == (0, body[2])
        udp.sendto(ic.datagram([ic.TAG_DISCONNECT], token), (HOST, server.port))


def test_error_packets_carry_only_the_codes_listed_for_them(
        session: ic.IndependentClient) -> None:
    """Doc 6.3, 6.6, 12.1, 12.2: which packet carries which code, and Error + Disconnect
    (never ConnectError) once a session exists."""
    topic = "/normative/codes"
    session.bind(1, "publish", topic, F64)
    cases: list[tuple[list[Any], int, int]] = [
        ([ic.TAG_TOPIC_CONNECT, 2, "both", topic, F64], ic.TAG_TOPIC_ERROR, ic.MALFORMED),
        (ic.topic_connect(3, "publish", topic, "std_msgs/msg/Nope"), ic.TAG_TOPIC_ERROR,
         ic.UNKNOWN_TYPE),
        ([99, 1], ic.TAG_ERROR, ic.MALFORMED),
        (ic.value(1, 0, 0, "x"), ic.TAG_ERROR, ic.BAD_VALUE),
        (ic.value(8, 0, 0, 1.0), ic.TAG_ERROR, ic.UNKNOWN_CHANNEL),
        (ic.hello("again"), ic.TAG_ERROR, ic.UNEXPECTED),
    ]
    for body, tag, code in cases:
        session.send_tcp(body)
        answer = session.recv_tag(tag)
        assert answer.field(2 if tag == ic.TAG_TOPIC_ERROR else 1) == code
        assert_carried(answer, code)
    session.send_raw_tcp(b"XX\x01\x00\x00\x00\x00\x01\x90")  # bad magic inside the session
    error = session.recv_tag(ic.TAG_ERROR, ic.TAG_CONNECT_ERROR)
    assert (error.name, error.field(1)) == ("Error", ic.MALFORMED)
    goodbye = session.recv_tag(ic.TAG_DISCONNECT)
    assert goodbye.field(1) == ic.MALFORMED
    assert_carried(goodbye, ic.MALFORMED)
    assert session.wait_eof()


def test_stale_duplicate_and_published_values_are_each_counted_once(
        session: ic.IndependentClient) -> None:
    """Doc 10.2, 13.2: a stale Value goes to late and overtaken, not duplicates; values_in
    counts what was published."""
    session.bind(4, "publish", "/normative/seq", F64, transport="udp")
    for seq in (5, 5, 3, 6):  # new, duplicate, stale, new
        session.send_udp(ic.value(4, seq, time.time_ns(), float(seq)))
    session.send_udp(ic.batch(4, 4, [0, 0, 0, 0], [4.0, 5.0, 6.0, 7.0]))  # 3 old, 1 new
    ch = session.stats(via="udp")["session"]["channels"]["4"]  # after those, same socket
    assert (ch["values_in"], ch["duplicates"], ch["late"], ch["overtaken"]) == (3, 4, 5, 1)
    assert ch["lost"] == 0


def test_rate_limit_error_names_the_channel(make_server: Callable[..., ServerThread]) -> None:
    """Doc 12.1, 12.2 LIMIT: Error(20) carries the channel of the packet that went over."""
    srv = make_server(max_rate=10)
    with ic.IndependentClient(HOST, srv.port, timeout=5) as c:
        c.connect_tcp("fast", with_udp=False)
        c.bind(7, "publish", "/normative/rate", F64)
        c.send_tcp(ic.batch(7, 0, [0] * 50, [1.0] * 50))
        err = c.recv_tag(ic.TAG_ERROR)
        assert (err.field(1), err.field(3)) == (ic.LIMIT, 7)
        assert_carried(err, ic.LIMIT)


# -- section 16 (a server with a key) --------------------------------------------------------
KEY = bytes(range(100, 132))


def lp(field: bytes) -> bytes:
    return struct.pack(">H", len(field)) + field


def test_transcript_notation_and_unsealed_handshake_datagrams(
        make_server: Callable[..., ServerThread], tmp_path: Path) -> None:
    """Doc 16.1: T = lp(00 01) || lp(name) || lp(Nc) || lp(Ns); handshake datagrams use
    token 0 unsealed, the ConnectAck is sealed under the new token (16.2, 16.3)."""
    keys = tmp_path / "keys"
    keys.write_text(f"{KEY.hex()}\n")
    srv = make_server(psk_file=keys)
    nc = os.urandom(16)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.settimeout(5)
        udp.connect((HOST, srv.port))
        udp.send(ic.datagram([ic.TAG_HELLO, 1, "n", nc], 0))
        flags, token, (tag, ns, _ps) = ic.parse_datagram(udp.recv(65536))
        assert (tag, flags, token) == (ic.TAG_AUTH_CHALLENGE, 0, 0)
        t = lp(b"\x00\x01") + lp(b"n") + lp(nc) + lp(ns)
        assert t[:4] == bytes.fromhex("00020001")  # as the document expands it
        label = b"rlbridge-psk-v1\0"
        pc = hmac.new(KEY, label + b"client-proof\0" + t, hashlib.sha256).digest()
        udp.send(ic.datagram([ic.TAG_STATS], 0))  # a token-0 stray: dropped (doc 16.1)
        udp.send(ic.datagram([ic.TAG_AUTH_PROOF, pc], 0))
        data = udp.recv(65536)
        magic, version, flags, token = ic.DATAGRAM_HEADER.unpack_from(data)
        assert (magic, version, flags & 1) == (b"RB", 1, 1)  # sealed
        # Doc 16.2: HKDF-SHA256(K, salt Nc || Ns, info "rlbridge-keys-v1\0" || T); Ks2c is
        # the second 32 bytes. Doc 16.3: ChaCha20-Poly1305, nonce 4 zero bytes || counter.
        prk = hmac.new(nc + ns, KEY, hashlib.sha256).digest()
        okm, block = b"", b""
        for i in (1, 2):
            block = hmac.new(prk, block + b"rlbridge-keys-v1\0" + t + bytes([i]),
                             hashlib.sha256).digest()
            okm += block
        s2c = okm[32:64]
        body = ic.unpackb(ChaCha20Poly1305(s2c).decrypt(bytes(4) + data[12:20], data[20:],
                                                        data[:20]))
        assert body[0] == ic.TAG_CONNECT_ACK
        assert body[2] == token


def test_wrong_frame_after_auth_challenge(make_server: Callable[..., ServerThread],
                                          tmp_path: Path) -> None:
    """Doc 16.1, 12.1, 6.3: anything but the proof after AuthChallenge is ConnectError(4)."""
    keys = tmp_path / "keys"
    keys.write_text(f"{KEY.hex()}\n")
    srv = make_server(psk_file=keys)
    with ic.IndependentClient(HOST, srv.port, timeout=5) as c:
        c.open_tcp()
        c.send_tcp([ic.TAG_HELLO, 1, "n", os.urandom(16)])
        c.recv_tag(ic.TAG_AUTH_CHALLENGE)
        c.send_tcp([ic.TAG_STATS])
        refused = c.recv_tag(ic.TAG_CONNECT_ERROR)
        assert refused.field(1) == ic.UNEXPECTED
        assert_carried(refused, ic.UNEXPECTED)
        assert c.wait_eof()


def test_section_14_dumps_are_what_the_server_encodes() -> None:
    """Doc 14: "generated with the reference codec" stays true for the packets that grew
    fields (TopicAck.schema, Error.values). The one place this file uses ``rlbridge.wire``."""
    from rlbridge.wire import Error, PacketCodec, TopicAck

    text = DOC.read_text()
    section = text[text.index("### 14.4") : text.index("### 14.5")]
    dump = re.search(r"```\n((?:[0-9a-f]{4}  .*\n)+)```", section)
    assert dump is not None
    raw = bytes.fromhex("".join(line[6:] for line in dump[1].splitlines()))
    codec = PacketCodec()
    assert bytes(codec.encode_frame(TopicAck(1, F64, 0.0))) == raw
    line = re.search(r'^Error\(13, "bad", 2, 0\): ([0-9a-f ]+)$', text, re.M)
    assert line is not None
    assert bytes(codec.encode_frame(Error(13, "bad", 2))) == bytes.fromhex(line[1])


def test_a_udp_answer_too_large_for_a_datagram_is_a_too_large_error(
        session: ic.IndependentClient) -> None:
    """Doc 3 (size), 12.2, 15.13: a Stats answer over 65 507 bytes is not sent over UDP; a
    small Error(3) takes its place and the server counts it; TCP carries the whole answer."""
    for channel in range(1, 201):  # each channel adds its counters and a 200-character topic
        session.bind(channel, "publish", f"/normative/big/c{channel:03d}/" + "t" * 180, F64)
    session.send_udp([ic.TAG_STATS])
    err = session.recv_tag(ic.TAG_ERROR, via="udp")
    assert (err.field(1), err.field(3)) == (ic.TOO_LARGE, None)
    assert "ask over TCP" in err.field(2)
    assert_carried(err, ic.TOO_LARGE)
    session.send_tcp([ic.TAG_STATS])
    answer = session.recv_tag(ic.TAG_STATS, via="tcp")
    assert len(ic.packb([ic.TAG_STATS, answer.field(1)])) > 65507
    assert answer.field(1)["server"]["udp_too_large_out"] == 1
