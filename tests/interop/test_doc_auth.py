"""docs/protocol.md section 16, implemented from the text alone: the PSK handshake over TCP,
sealed TCP records and sealed datagrams both ways, with the standard library (HKDF from RFC
5869 written out), ``cryptography``'s ChaCha20-Poly1305 and the independent client's
MessagePack subset (nothing from ``rlbridge``), against a real server started with a key file;
and the document's test vectors recomputed the same way."""

from __future__ import annotations

import hashlib
import hmac
import os
import socket
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import independent_client as ic
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305

from rlbridge.server import ServerThread

KEY = bytes(range(200, 232))
LABEL = b"rlbridge-psk-v1\0"


def transcript(name: str, nc: bytes, ns: bytes) -> bytes:
    """Doc 16.1: each field preceded by its length as a big-endian u16."""
    fields = [(1).to_bytes(2, "big"), name.encode(), nc, ns]
    return b"".join(struct.pack(">H", len(f)) + f for f in fields)


def prf(purpose: bytes, t: bytes) -> bytes:
    return hmac.new(KEY, LABEL + purpose + b"\0" + t, hashlib.sha256).digest()


def hkdf(ikm: bytes, salt: bytes, info: bytes, length: int) -> bytes:
    """RFC 5869 with SHA-256."""
    prk = hmac.new(salt or bytes(32), ikm, hashlib.sha256).digest()
    okm, block = b"", b""
    for i in range(1, -(-length // 32) + 1):
        block = hmac.new(prk, block + info + bytes([i]), hashlib.sha256).digest()
        okm += block
    return okm[:length]


def session_keys(nc: bytes, ns: bytes, t: bytes) -> list[bytes]:
    """Doc 16.2: Kc2s, Ks2c, Rc2s, Rs2c."""
    okm = hkdf(KEY, nc + ns, b"rlbridge-keys-v1\0" + t, 128)
    return [okm[i:i + 32] for i in range(0, 128, 32)]


def nonce(counter: int) -> bytes:
    return bytes(4) + struct.pack(">Q", counter)


def seal(token: int, counter: int, body: list[Any], key: bytes) -> bytes:
    """Doc 16.3: header with SEALED, u64 counter, then the AEAD over the body."""
    head = struct.pack(">2sBBQ", b"RB", 1, 0x01, token) + struct.pack(">Q", counter)
    return head + ChaCha20Poly1305(key).encrypt(nonce(counter), ic.packb(body), head)


def unseal(data: bytes, key: bytes) -> tuple[int, Any]:
    magic, version, flags, _token = struct.unpack_from(">2sBBQ", data)
    assert (magic, version, flags & 1) == (b"RB", 1, 1)
    (counter,) = struct.unpack_from(">Q", data, 12)
    body = ChaCha20Poly1305(key).decrypt(nonce(counter), data[20:], data[:20])
    return counter, ic.unpackb(body)


class Records:
    """Doc 16.5: one direction's records, counter implicit from 0."""

    def __init__(self, key: bytes) -> None:
        self.aead = ChaCha20Poly1305(key)
        self.counter = 0
        self.buf = b""

    def seal(self, frames: bytes) -> bytes:
        head = struct.pack(">2sBBI", b"RB", 1, 0x01, len(frames) + 16)
        out = head + self.aead.encrypt(nonce(self.counter), frames, head)
        self.counter += 1
        return out

    def open(self, data: bytes) -> bytes:
        """The frame bytes inside the whole records of ``buf + data``."""
        self.buf += data
        plain = b""
        while len(self.buf) >= 8:
            _magic, _version, flags, length = struct.unpack_from(">2sBBI", self.buf)
            assert flags & 1, "a plain frame after the handshake"
            if len(self.buf) < 8 + length:
                break
            plain += self.aead.decrypt(nonce(self.counter), self.buf[8:8 + length],
                                       self.buf[:8])
            self.counter += 1
            self.buf = self.buf[8 + length:]
        return plain


def test_handshake_and_sealed_datagrams_from_the_document(
        make_server: Callable[..., ServerThread], tmp_path: Path) -> None:
    keys = tmp_path / "keys"
    keys.write_text(f"docs {KEY.hex()}\n")
    srv = make_server(psk_file=keys)
    nc = os.urandom(16)
    reader = ic.FrameReader()
    with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as tcp, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        tcp.sendall(ic.frame([ic.TAG_HELLO, 1, "docs", nc]))
        tag, ns, server_proof = reader.feed(tcp.recv(65536))[0]
        assert tag == ic.TAG_AUTH_CHALLENGE
        t = transcript("docs", nc, ns)
        assert hmac.compare_digest(server_proof, prf(b"server-proof", t))
        tcp.sendall(ic.frame([ic.TAG_AUTH_PROOF, prf(b"client-proof", t)]))
        c2s, s2c, r_c2s, r_s2c = session_keys(nc, ns, t)
        to_server, from_server = Records(r_c2s), Records(r_s2c)
        bodies: list[Any] = []
        while not bodies:
            bodies = reader.feed(from_server.open(tcp.recv(65536)))
        ack = bodies[0]
        assert ack[0] == ic.TAG_CONNECT_ACK, ack
        token = ack[2]
        tcp.sendall(to_server.seal(ic.frame([ic.TAG_STATS])))
        while not any(b[0] == ic.TAG_STATS for b in bodies):
            bodies += reader.feed(from_server.open(tcp.recv(65536)))

        udp.settimeout(10)
        udp.connect(("127.0.0.1", srv.port))
        udp.send(seal(token, 1, [ic.TAG_STATS], c2s))
        while True:
            counter, body = unseal(udp.recv(65536), s2c)
            if body[0] == ic.TAG_STATS:
                break
        assert counter >= 1
        assert body[1]["server"]["sessions_authenticated"] == 1
        udp.send(seal(token, 1, [ic.TAG_STATS], c2s))  # the same counter again: a replay
        udp.send(seal(token, 2, [ic.TAG_STATS], c2s))
        while True:
            _counter, body = unseal(udp.recv(65536), s2c)
            if body[0] == ic.TAG_STATS:
                break
        assert body[1]["server"]["udp_replayed"] == 1


def test_the_documents_test_vectors() -> None:
    """Doc 16.6, recomputed from sections 16.1-16.5 and compared with the text."""
    doc = (Path(__file__).parents[2] / "docs" / "protocol.md").read_text()
    vectors = doc[doc.index("### 16.6 Test vectors"):]
    key = bytes(range(32))
    nc, ns = bytes(range(16)), bytes(range(16, 32))
    t = transcript("robot", nc, ns)
    okm = hkdf(key, nc + ns, b"rlbridge-keys-v1\0" + t, 128)
    label = b"rlbridge-psk-v1\0"
    expected = {
        "T": t,
        "Ps": hmac.new(key, label + b"server-proof\0" + t, hashlib.sha256).digest(),
        "Pc": hmac.new(key, label + b"client-proof\0" + t, hashlib.sha256).digest(),
        "Kc2s": okm[:32], "Ks2c": okm[32:64], "Rc2s": okm[64:96], "Rs2c": okm[96:],
    }
    for name, value in expected.items():
        assert f"{name:<4} = {value.hex()}" in vectors, name
    body = bytes.fromhex("9508010000cb3ff8000000000000")
    assert ic.unpackb(body) == [ic.TAG_VALUE, 1, 0, 0, 1.5]
    head = struct.pack(">2sBBQ", b"RB", 1, 1, 0x0102030405060708) + struct.pack(">Q", 1)
    datagram = head + ChaCha20Poly1305(okm[:32]).encrypt(nonce(1), body, head)
    assert datagram.hex() in vectors
    frame = ic.frame([ic.TAG_HEARTBEAT, 1, 0, 0, 0, 0])  # all fields written
    assert frame.hex() == "5242010000000007960a0100000000"
    head = struct.pack(">2sBBI", b"RB", 1, 1, len(frame) + 16)
    record = head + ChaCha20Poly1305(okm[64:96]).encrypt(nonce(0), frame, head)
    assert record.hex() in vectors
    tls = hkdf(bytes(range(64, 96)), b"", b"rlbridge-keys-v1\0tls\0"
               + (0x0102030405060708).to_bytes(8, "big"), 128)
    assert f"Kc2s = {tls[:32].hex()}" in vectors
    assert f"Ks2c = {tls[32:64].hex()}" in vectors
