"""docs/protocol.md section 16, implemented from the text alone: the PSK handshake over TCP and
sealed datagrams both ways, with the standard library and the independent client's MessagePack
subset (nothing from ``rlbridge.wire``), against a real server started with a key file."""

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

from rlbridge.server import ServerThread

KEY = bytes(range(200, 232))
LABEL = b"rlbridge-psk-v1\0"


def transcript(name: str, nc: bytes, ns: bytes) -> bytes:
    """Doc 16.1: each field preceded by its length as a big-endian u16."""
    fields = [(1).to_bytes(2, "big"), name.encode(), nc, ns]
    return b"".join(struct.pack(">H", len(f)) + f for f in fields)


def prf(purpose: bytes, t: bytes) -> bytes:
    return hmac.new(KEY, LABEL + purpose + b"\0" + t, hashlib.sha256).digest()


def seal(token: int, counter: int, body: list[Any], key: bytes) -> bytes:
    """Doc 16.3: header with FLAG_MAC, u64 counter, body, BLAKE2s-128 over all of it."""
    data = struct.pack(">2sBBQ", b"RB", 1, 0x01, token) + struct.pack(">Q", counter) + ic.packb(
        body)
    return data + hashlib.blake2s(data, key=key, digest_size=16).digest()


def unseal(data: bytes, key: bytes) -> tuple[int, Any]:
    magic, version, flags, _token = struct.unpack_from(">2sBBQ", data)
    assert (magic, version, flags & 1) == (b"RB", 1, 1)
    mac = hashlib.blake2s(data[:-16], key=key, digest_size=16).digest()
    assert hmac.compare_digest(mac, data[-16:]), "the server's seal does not verify"
    (counter,) = struct.unpack_from(">Q", data, 12)
    return counter, ic.unpackb(data[20:-16])


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
        bodies: list[Any] = []
        while not bodies:
            bodies = reader.feed(tcp.recv(65536))
        ack = bodies[0]
        assert ack[0] == ic.TAG_CONNECT_ACK, ack
        token = ack[2]
        c2s, s2c = prf(b"c2s", t), prf(b"s2c", t)

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
