"""PSK handshake, datagram sealing and the replay window, sans-IO: no sockets, fixed nonces."""

from __future__ import annotations

import msgspec
import pytest
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
from hypothesis import given, settings
from hypothesis import strategies as st

from rlbridge import ErrorCode, RemoteProtocolError
from rlbridge.wire import (
    DATAGRAM_HEADER,
    MAGIC,
    PROTOCOL_VERSION,
    AuthChallenge,
    Batch,
    Bundle,
    Value,
)
from rlbridge.wire.auth import (
    COUNTER,
    SEAL_OVERHEAD,
    ClientHandshake,
    DatagramRejected,
    ReplayWindow,
    ServerHandshake,
    SessionKeys,
    parse_key,
    sealed_codec,
)
from rlbridge.wire.bundle import DatagramPacker
from rlbridge.wire.codec import FLAG_BUNDLES, FLAG_MAC, PacketCodec, peek_header

KEY = bytes(range(32))
OTHER = bytes(range(1, 33))
CN, SN = b"c" * 16, b"s" * 16


def handshake(client_key: bytes = KEY, server_key: bytes = KEY, name: str = "robot"
              ) -> tuple[ClientHandshake, ServerHandshake]:
    return ClientHandshake(client_key, name, CN), ServerHandshake(server_key, name, CN, SN)


def session() -> tuple[SessionKeys, SessionKeys]:
    client, server = handshake()
    server_keys = server.verify(client.answer(server.challenge))
    assert client.keys is not None
    return client.keys, server_keys


def test_handshake_with_the_same_key_gives_both_sides_the_same_keys() -> None:
    client_keys, server_keys = session()
    assert client_keys == server_keys
    assert client_keys.client_to_server != client_keys.server_to_client
    assert KEY not in (client_keys.client_to_server, client_keys.server_to_client)


def test_answer_is_idempotent_for_a_retransmitted_challenge() -> None:
    client, server = handshake()
    assert client.answer(server.challenge) == client.answer(server.challenge)


def test_client_with_a_wrong_key_is_refused_by_the_server() -> None:
    # The client cannot even answer: the server's proof does not match its key (mutual).
    client, server = handshake(client_key=OTHER)
    with pytest.raises(RemoteProtocolError, match="could not prove") as exc:
        client.answer(server.challenge)
    assert exc.value.code == ErrorCode.AUTH_FAILED
    # And a proof made with another key does not pass the server either.
    liar = ClientHandshake(OTHER, "robot", CN)
    other_server = ServerHandshake(OTHER, "robot", CN, SN)
    with pytest.raises(RemoteProtocolError, match="does not match") as exc:
        server.verify(liar.answer(other_server.challenge))
    assert exc.value.code == ErrorCode.AUTH_FAILED


@pytest.mark.parametrize("field", ["name", "client_nonce", "server_nonce"])
def test_the_proof_binds_the_name_and_both_nonces(field: str) -> None:
    """A proof recorded for one transcript is worthless in any other."""
    client, server = handshake()
    proof = client.answer(server.challenge)
    other = {"name": ("robot2", CN, SN), "client_nonce": ("robot", b"d" * 16, SN),
             "server_nonce": ("robot", CN, b"t" * 16)}[field]
    with pytest.raises(RemoteProtocolError):
        ServerHandshake(KEY, *other).verify(proof)


def test_forged_server_proof_is_refused() -> None:
    client, server = handshake()
    forged = AuthChallenge(server.challenge.nonce, bytes(32))
    with pytest.raises(RemoteProtocolError):
        client.answer(forged)


def test_hello_without_a_nonce_is_refused_with_a_reason() -> None:
    with pytest.raises(RemoteProtocolError, match="requires a pre-shared key") as exc:
        ServerHandshake(KEY, "robot", b"", SN)
    assert exc.value.code == ErrorCode.AUTH_FAILED


@pytest.mark.parametrize("body", [[15, b"x" * 31], [15, b"x" * 33], [15, "x" * 32],
                                  [14, b"n" * 15, b"p" * 32], [14, b"n" * 16]])
def test_auth_packets_of_the_wrong_shape_do_not_decode(body: list[object]) -> None:
    with pytest.raises(RemoteProtocolError) as exc:
        PacketCodec().decode_body(msgspec.msgpack.encode(body))
    assert exc.value.code == ErrorCode.MALFORMED


# -- sealed datagrams -----------------------------------------------------------------------


def pair() -> tuple[PacketCodec, PacketCodec]:
    client_keys, server_keys = session()
    return sealed_codec(client_keys, server=False), sealed_codec(server_keys, server=True)


def test_sealed_round_trip_both_ways() -> None:
    client, server = pair()
    data = client.encode_datagram(Value(1, 2, 3, 4.5), token=77)
    assert data[3] & FLAG_MAC
    assert len(data) == len(PacketCodec().encode_datagram(Value(1, 2, 3, 4.5), 77)) + SEAL_OVERHEAD
    assert server.decode_datagram(data) == (FLAG_MAC, 77, Value(1, 2, 3, 4.5))
    back = server.encode_datagram(Value(9, 1, 1, "x"), token=77)
    assert client.decode_datagram(back)[2] == Value(9, 1, 1, "x")


def test_every_flipped_bit_is_refused() -> None:
    client, server = pair()
    data = client.encode_datagram(Value(1, 2, 3, 4.5), token=77)
    for i in range(len(data)):
        for bit in (0x01, 0x80):
            forged = bytearray(data)
            forged[i] ^= bit
            with pytest.raises(RemoteProtocolError):
                server.decode_datagram(bytes(forged))
    assert server.decode_datagram(data)[2] == Value(1, 2, 3, 4.5)  # the original still passes


def test_replayed_and_reflected_and_unsealed_datagrams() -> None:
    client, server = pair()
    data = client.encode_datagram(Value(1, 2, 3, 4.5), token=77)
    server.decode_datagram(data)
    with pytest.raises(DatagramRejected) as exc:
        server.decode_datagram(data)
    assert exc.value.kind == "replayed"
    # The server's own datagram sent back to it: wrong direction key.
    with pytest.raises(DatagramRejected) as exc:
        server.decode_datagram(server.encode_datagram(Value(1, 3, 3, 4.5), token=77))
    assert exc.value.kind == "bad_mac"
    with pytest.raises(DatagramRejected) as exc:
        server.decode_datagram(PacketCodec().encode_datagram(Value(1, 2, 3, 4.5), 77))
    assert exc.value.kind == "unsealed"
    # Another session's keys (another server nonce) do not verify either.
    other_client = ClientHandshake(KEY, "robot", CN)
    other_client.answer(ServerHandshake(KEY, "robot", CN, b"z" * 16).challenge)
    assert other_client.keys is not None
    stranger = sealed_codec(other_client.keys, server=False)
    with pytest.raises(DatagramRejected) as exc:
        server.decode_datagram(stranger.encode_datagram(Value(1, 2, 3, 4.5), 77))
    assert exc.value.kind == "bad_mac"


def test_truncated_sealed_datagrams_are_refused() -> None:
    client, server = pair()
    data = client.encode_datagram(Value(1, 2, 3, 4.5), token=77)
    for n in range(len(data)):
        with pytest.raises(RemoteProtocolError):
            server.decode_datagram(data[:n])


def test_bad_body_inside_a_valid_seal_is_malformed_not_forged() -> None:
    """A seal that opens proves the sender: its bad body is a MALFORMED error it may hear."""
    client_keys, server_keys = session()
    server = sealed_codec(server_keys, server=True)
    head = DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, FLAG_MAC, 77) + COUNTER.pack(1)
    sealed = ChaCha20Poly1305(client_keys.client_to_server).encrypt(
        b"\0" * 4 + COUNTER.pack(1), b"\x95\x08\x03\xa1x\x00\x01", head)
    with pytest.raises(RemoteProtocolError) as exc:
        server.decode_datagram(head + sealed)
    assert not isinstance(exc.value, DatagramRejected)
    assert (exc.value.code, exc.value.token, exc.value.channel) == (ErrorCode.MALFORMED, 77, 3)



def test_packer_seals_exactly_the_bytes_the_codec_encodes() -> None:
    """The packer seals the parts' own encodings (no second encoding): each datagram opens to
    the bytes msgspec gives for the same packet, a value alone or a bundle of parts."""
    client_keys, server_keys = session()
    client = sealed_codec(client_keys, server=False)
    server = sealed_codec(server_keys, server=True)
    sent: list[bytes] = []
    packer = DatagramPacker(client, 77, 1400, sent.append, flags=FLAG_BUNDLES)
    alone = Value(1, 5, 6, 1.5)
    parts: list[Value | Batch] = [Value(1, 6, 7, 2.5), Batch(2, 8, [9, 10], [3.5, 4.5])]
    packer.add(alone)
    packer.flush()
    for part in parts:
        packer.add(part)
    packer.flush()
    cipher = ChaCha20Poly1305(client_keys.client_to_server)
    for data, packet in zip(sent, [alone, Bundle(parts)], strict=True):
        flags, token, got = server.decode_datagram(data)
        assert (got, token, flags & FLAG_BUNDLES) == (packet, 77, FLAG_BUNDLES)
        head = DATAGRAM_HEADER.size + COUNTER.size
        body = cipher.decrypt(b"\0" * 4 + data[DATAGRAM_HEADER.size:head], data[head:],
                              data[:head])
        assert body == msgspec.msgpack.encode(packet)


# -- replay window --------------------------------------------------------------------------


@settings(deadline=None, max_examples=200)
@given(st.lists(st.integers(0, 3000), max_size=300), st.sampled_from([8, 64, 1024]))
def test_replay_window_matches_a_model(counters: list[int], size: int) -> None:
    """Accept a counter iff it is > 0, never accepted before, and within ``size`` of the top."""
    window = ReplayWindow(size)
    accepted: set[int] = set()
    top = 0
    for c in counters:
        expected = c > 0 and c not in accepted and c > top - size
        assert window.check(c) is expected, (c, top)
        if expected:
            accepted.add(c)
            top = max(top, c)


def test_replay_window_keeps_reordered_datagrams() -> None:
    window = ReplayWindow(64)
    assert all(window.check(c) for c in (1, 3, 2, 10, 5, 4))
    assert not window.check(3)
    assert window.check(10 + 63)
    assert not window.check(9)


# -- keys -----------------------------------------------------------------------------------


def test_parse_key() -> None:
    assert parse_key(" " + KEY.hex() + "\n", "x") == KEY
    with pytest.raises(ValueError, match="in hex"):
        parse_key("not-hex", "the file, line 1")
    with pytest.raises(ValueError, match="too short"):
        parse_key("00" * 8, "x")


@settings(deadline=None, max_examples=300)
@given(st.lists(st.binary(max_size=80), max_size=20))
def test_junk_raises_only_protocol_errors_and_never_moves_the_window(junk: list[bytes]) -> None:
    """A forger cannot push the window ahead (which would make genuine datagrams 'old')."""
    client, server = pair()
    for data in junk:
        # Make some of them look sealed, with a huge counter, to tempt the window.
        forged = (DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, FLAG_MAC, 77)
                  + COUNTER.pack(2**63) + data)
        for datagram in (data, forged):
            with pytest.raises(RemoteProtocolError):
                server.decode_datagram(datagram)
    assert server.decode_datagram(client.encode_datagram(Value(1, 2, 3, 4.5), 77))[1] == 77


def test_peek_header() -> None:
    data = PacketCodec().encode_datagram(Value(1, 2, 3, 4.5), 2**64 - 1, flags=FLAG_MAC)
    assert peek_header(data) == (FLAG_MAC, 2**64 - 1)
    assert peek_header(data[:11]) == (0, 0)
    assert peek_header(b"XX" + data[2:]) == (0, 0)
    assert peek_header(data[:2] + b"\x09" + data[3:]) == (0, 0)
