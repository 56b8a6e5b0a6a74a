"""Pre-shared-key authentication, sans-IO (no sockets, no clocks, no RNG).

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
protocol, role or session can be replayed here. Both sides then derive the session's keys with
HKDF over the key, both nonces and ``T`` (:func:`rlbridge.wire.seal.derive_keys`): everything
after the handshake, datagrams and (without TLS) TCP frames, is sealed with them.
Randomness (the nonces) is passed in by the caller, as time is elsewhere in ``wire/``.
"""

from __future__ import annotations

import hmac

from rlbridge.errors import ErrorCode, RemoteProtocolError
from rlbridge.wire.packets import PROTOCOL_VERSION, AuthChallenge, AuthProof
from rlbridge.wire.seal import (
    COUNTER,
    REPLAY_WINDOW,
    SEAL_OVERHEAD,
    TAG_SIZE,
    DatagramRejected,
    ReplayWindow,
    SealedCodec,
    SessionKeys,
    derive_keys,
    sealed_codec,
)

__all__ = ["COUNTER", "MIN_KEY_SIZE", "NONCE_SIZE", "PSK_ENV", "REPLAY_WINDOW", "SEAL_OVERHEAD",
           "TAG_SIZE", "ClientHandshake", "DatagramRejected", "ReplayWindow", "SealedCodec",
           "ServerHandshake", "SessionKeys", "parse_key", "sealed_codec"]

#: Environment variable holding a key in hex, read by the server and the SDK alike.
PSK_ENV = "RLBRIDGE_PSK"
NONCE_SIZE = 16
#: Keys shorter than this are refused when loaded: a PSK is not a password.
MIN_KEY_SIZE = 16
_LABEL = b"rlbridge-psk-v1\x00"


def _transcript(name: str, client_nonce: bytes, server_nonce: bytes) -> bytes:
    parts = [PROTOCOL_VERSION.to_bytes(2, "big"), name.encode(), client_nonce, server_nonce]
    return b"".join(len(p).to_bytes(2, "big") + p for p in parts)


def _prf(key: bytes, purpose: bytes, transcript: bytes) -> bytes:
    return hmac.digest(key, _LABEL + purpose + b"\x00" + transcript, "sha256")


def _keys(key: bytes, client_nonce: bytes, server_nonce: bytes, transcript: bytes
          ) -> SessionKeys:
    return derive_keys(key, client_nonce + server_nonce, transcript)


class ServerHandshake:
    """The server's half for one hello: issue the challenge, check the proof."""

    def __init__(self, key: bytes, name: str, client_nonce: bytes, server_nonce: bytes) -> None:
        if len(client_nonce) != NONCE_SIZE:
            raise RemoteProtocolError(
                ErrorCode.AUTH_FAILED,
                "this server requires a pre-shared key and this client gave none: give it "
                f"the server's key (${PSK_ENV}, see docs/security.md)")
        self._key = key
        self._nonces = (client_nonce, server_nonce)
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
        return _keys(self._key, *self._nonces, self._transcript)


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
        self.keys = _keys(self._key, self.nonce, challenge.nonce, transcript)
        return AuthProof(_prf(self._key, b"client-proof", transcript))


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
