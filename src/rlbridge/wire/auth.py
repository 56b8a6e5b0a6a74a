"""Pre-shared-key authentication and datagram MACs, sans-IO (no sockets, no clocks, no RNG).

Theory of operation (docs/security.md has the threat model). With a pre-shared key ``K`` the
handshake is a nonce exchange answered with HMAC-SHA256:

1. client -> ``Hello(name, auth=Nc)``, ``Nc`` 16 random bytes;
2. server -> ``AuthChallenge(Ns, server_proof)``, ``Ns`` 16 random bytes and
   ``server_proof = HMAC(K, "server-proof" | T)``, so the client learns the server knows ``K``
   before it sends anything that depends on it (mutual proof);
3. client -> ``AuthProof(HMAC(K, "client-proof" | T))``; server compares in constant time and
   answers ``ConnectAck`` or ``ConnectError(AUTH_FAILED)``.

``T`` is the transcript: a domain label, the protocol version, the client's name and both
nonces, each length-prefixed, so no field can be shifted into another and no proof from another
protocol, role or session can be replayed here. Both sides then derive two per-session keys
(client-to-server and server-to-client: a datagram reflected back at its sender does not
verify) as HMAC(K, "c2s" | T) and HMAC(K, "s2c" | T).

A sealed datagram (header flag ``FLAG_MAC``) is ``header | counter (u64) | body | tag`` where
``tag`` is keyed BLAKE2s-128 over everything before it. The counter increases by one per
datagram; the receiver keeps a sliding window of the last ``REPLAY_WINDOW`` counters, so a
datagram repeated, or older than the window, is refused even though its MAC is valid.
Randomness (the nonces) is passed in by the caller, as time is elsewhere in ``wire/``.
"""

from __future__ import annotations

import hashlib
import hmac
import itertools
import struct
from dataclasses import dataclass

from rlbridge.wire.codec import DATAGRAM_HEADER, FLAG_MAC, MAGIC, PacketCodec, check_header
from rlbridge.wire.errors import ErrorCode, RemoteProtocolError
from rlbridge.wire.packets import PROTOCOL_VERSION, AuthChallenge, AuthProof, Packet

#: Environment variable holding a key in hex, read by the server and the SDK alike.
PSK_ENV = "RLBRIDGE_PSK"
NONCE_SIZE = 16
#: Keys shorter than this are refused when loaded: a PSK is not a password.
MIN_KEY_SIZE = 16
TAG_SIZE = 16
COUNTER = struct.Struct(">Q")
#: Bytes a sealed datagram carries beyond an unsealed one.
SEAL_OVERHEAD = COUNTER.size + TAG_SIZE
#: Counters remembered behind the highest one seen (IPsec uses 32-1024; reordering here is
#: a burst of a few datagrams, plus redundancy copies).
REPLAY_WINDOW = 1024
_LABEL = b"rlbridge-psk-v1\x00"


def _transcript(name: str, client_nonce: bytes, server_nonce: bytes) -> bytes:
    parts = [PROTOCOL_VERSION.to_bytes(2, "big"), name.encode(), client_nonce, server_nonce]
    return b"".join(len(p).to_bytes(2, "big") + p for p in parts)


def _prf(key: bytes, purpose: bytes, transcript: bytes) -> bytes:
    return hmac.digest(key, _LABEL + purpose + b"\x00" + transcript, "sha256")


@dataclass(frozen=True, slots=True)
class SessionKeys:
    """The two directional datagram keys of one authenticated session."""

    client_to_server: bytes
    server_to_client: bytes

    @classmethod
    def derive(cls, key: bytes, transcript: bytes) -> SessionKeys:
        return cls(_prf(key, b"c2s", transcript), _prf(key, b"s2c", transcript))


class ServerHandshake:
    """The server's half for one hello: issue the challenge, check the proof."""

    def __init__(self, key: bytes, name: str, client_nonce: bytes, server_nonce: bytes) -> None:
        if len(client_nonce) != NONCE_SIZE:
            raise RemoteProtocolError(
                ErrorCode.AUTH_FAILED,
                "this server requires a pre-shared key and this client gave none: give it "
                f"the server's key (${PSK_ENV}, see docs/security.md)")
        self._key = key
        self._transcript = _transcript(name, client_nonce, server_nonce)
        self.challenge = AuthChallenge(server_nonce, _prf(key, b"server-proof", self._transcript))

    def verify(self, proof: AuthProof) -> SessionKeys:
        """The session keys, or :class:`RemoteProtocolError` (AUTH_FAILED) for a wrong key."""
        expected = _prf(self._key, b"client-proof", self._transcript)
        if not hmac.compare_digest(expected, proof.proof):
            raise RemoteProtocolError(
                ErrorCode.AUTH_FAILED,
                "authentication failed: the client's proof does not match this server's "
                "pre-shared key for that client name")
        return SessionKeys.derive(self._key, self._transcript)


class ClientHandshake:
    """The client's half: the hello's nonce, then check the server and prove the key."""

    def __init__(self, key: bytes, name: str, client_nonce: bytes) -> None:
        if len(client_nonce) != NONCE_SIZE:
            raise ValueError(f"client nonce must be {NONCE_SIZE} bytes")
        self._key = key
        self._name = name
        self.nonce = client_nonce
        self.keys: SessionKeys | None = None

    def answer(self, challenge: AuthChallenge) -> AuthProof:
        """The proof for ``challenge``; raises AUTH_FAILED when the server does not know the key.

        Idempotent for a retransmitted challenge (same nonce, same answer).
        """
        transcript = _transcript(self._name, self.nonce, challenge.nonce)
        expected = _prf(self._key, b"server-proof", transcript)
        if not hmac.compare_digest(expected, challenge.proof):
            raise RemoteProtocolError(
                ErrorCode.AUTH_FAILED,
                "the server could not prove it knows the pre-shared key (wrong key on one "
                "side, or not the server you meant)")
        self.keys = SessionKeys.derive(self._key, transcript)
        return AuthProof(_prf(self._key, b"client-proof", transcript))


class DatagramRejected(RemoteProtocolError):
    """A datagram refused by the MAC layer; ``kind`` names the counter it is dropped under."""

    def __init__(self, kind: str, reason: str) -> None:
        super().__init__(ErrorCode.AUTH_FAILED, reason)
        self.kind = kind


class ReplayWindow:
    """Which counters were already accepted: the highest, and a bitmap of those behind it."""

    def __init__(self, size: int = REPLAY_WINDOW) -> None:
        self._size = size
        self._top = 0
        self._seen = 0  # bit i set: counter ``top - i`` was accepted

    def check(self, counter: int) -> bool:
        """True if ``counter`` is new (and now remembered); False if repeated or too old."""
        if counter > self._top:
            shift = counter - self._top
            self._seen = ((self._seen << shift) | 1) & ((1 << self._size) - 1)
            self._top = counter
            return True
        behind = self._top - counter
        if counter == 0 or behind >= self._size or self._seen >> behind & 1:
            return False
        self._seen |= 1 << behind
        return True


class SealedCodec(PacketCodec):
    """A :class:`PacketCodec` whose datagrams carry a counter and a MAC (TCP frames do not).

    One per session and side: ``send_key`` seals, ``receive_key`` verifies. Every datagram
    must be sealed; an unsealed one, a wrong tag and a replayed counter raise
    :class:`DatagramRejected`. The counter is an ``itertools.count``, whose ``next`` is atomic
    under the GIL, so the client's threads may seal concurrently.
    """

    def __init__(self, send_key: bytes, receive_key: bytes) -> None:
        super().__init__()
        self._send_key = send_key
        self._receive_key = receive_key
        self._counter = itertools.count(1)
        self.window = ReplayWindow()

    def encode_datagram(self, packet: Packet, token: int, flags: int = 0) -> bytes:
        start = DATAGRAM_HEADER.size + COUNTER.size
        buf = bytearray(start)
        self._encoder.encode_into(packet, buf, start)
        DATAGRAM_HEADER.pack_into(buf, 0, MAGIC, PROTOCOL_VERSION, flags | FLAG_MAC, token)
        COUNTER.pack_into(buf, DATAGRAM_HEADER.size, next(self._counter))
        buf += hashlib.blake2s(buf, key=self._send_key, digest_size=TAG_SIZE).digest()
        return bytes(buf)

    def decode_datagram(self, data: bytes) -> tuple[int, int, Packet]:
        start = DATAGRAM_HEADER.size + COUNTER.size
        if len(data) < start + TAG_SIZE:
            raise DatagramRejected("unsealed", f"datagram of {len(data)} bytes is too short "
                                   "to carry a counter and a MAC")
        magic, version, flags, token = DATAGRAM_HEADER.unpack_from(data)
        check_header(magic, version)
        if not flags & FLAG_MAC:
            raise DatagramRejected("unsealed", "datagram without a MAC on an authenticated "
                                   "session")
        view = memoryview(data)
        end = len(data) - TAG_SIZE
        tag = hashlib.blake2s(view[:end], key=self._receive_key, digest_size=TAG_SIZE).digest()
        if not hmac.compare_digest(tag, view[end:]):
            raise DatagramRejected("bad_mac", "datagram MAC does not verify")
        (counter,) = COUNTER.unpack_from(data, DATAGRAM_HEADER.size)
        if not self.window.check(counter):
            raise DatagramRejected("replayed", f"datagram counter {counter} was already "
                                   "seen or is older than the replay window")
        try:
            return flags, token, self.decode_body(view[start:end])
        except RemoteProtocolError as exc:
            exc.token = token
            raise


def sealed_codec(keys: SessionKeys, *, server: bool) -> SealedCodec:
    """The codec one side of an authenticated session seals and opens datagrams with."""
    if server:
        return SealedCodec(keys.server_to_client, keys.client_to_server)
    return SealedCodec(keys.client_to_server, keys.server_to_client)


def parse_key(text: str, where: str) -> bytes:
    """A key written as hex (at least ``MIN_KEY_SIZE`` bytes); ``ValueError`` names ``where``."""
    try:
        key = bytes.fromhex(text.strip())
    except ValueError:
        raise ValueError(f"{where}: a key must be written in hex (e.g. from "
                         "`openssl rand -hex 32`)") from None
    if len(key) < MIN_KEY_SIZE:
        raise ValueError(f"{where}: key of {len(key)} bytes is too short; use at least "
                         f"{MIN_KEY_SIZE} random bytes (`openssl rand -hex 32`)")
    return key
