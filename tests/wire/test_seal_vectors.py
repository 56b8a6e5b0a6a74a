"""rlbridge's sealing reproduces docs/protocol.md section 16.6 byte for byte (sans-IO)."""

from __future__ import annotations

import re
from pathlib import Path

from rlbridge.wire import Heartbeat, PacketCodec, Value
from rlbridge.wire.auth import ClientHandshake, ServerHandshake
from rlbridge.wire.records import stream_sealers
from rlbridge.wire.seal import sealed_codec, tls_datagram_keys

DOC = (Path(__file__).parents[2] / "docs" / "protocol.md").read_text()
VECTORS = DOC[DOC.index("### 16.6 Test vectors"):]


def vector(name: str) -> str:
    match = re.search(rf"^{name}\s*= ([0-9a-f]+)$", VECTORS, re.M)
    assert match is not None, name
    return match.group(1)


def test_handshake_keys_datagram_and_record_match_the_document() -> None:
    key, nc, ns = bytes(range(32)), bytes(range(16)), bytes(range(16, 32))
    server = ServerHandshake(key, "robot", nc, ns)
    client = ClientHandshake(key, "robot", nc)
    proof = client.answer(server.challenge)
    keys = server.verify(proof)
    assert server.challenge.proof.hex() == vector("Ps")
    assert proof.proof.hex() == vector("Pc")
    assert keys.client_to_server.hex() == vector("Kc2s")
    assert keys.server_to_client.hex() == vector("Ks2c")
    assert keys.stream_client_to_server.hex() == vector("Rc2s")
    assert keys.stream_server_to_client.hex() == vector("Rs2c")
    datagram = sealed_codec(keys, server=False).encode_datagram(Value(1, 0, 0, 1.5),
                                                                0x0102030405060708)
    assert datagram.hex() in VECTORS
    assert sealed_codec(keys, server=True).decode_datagram(datagram)[2] == Value(1, 0, 0, 1.5)
    sealer, _ = stream_sealers(keys, server=False)
    assert sealer.seal(PacketCodec().encode_frame(Heartbeat(1))).hex() in VECTORS


def test_tls_datagram_keys_match_the_document() -> None:
    keys = tls_datagram_keys(bytes(range(64, 96)), 0x0102030405060708)
    tls_part = VECTORS[VECTORS.index("TLS datagram keys"):]
    assert f"Kc2s = {keys.client_to_server.hex()}" in tls_part
    assert f"Ks2c = {keys.server_to_client.hex()}" in tls_part
