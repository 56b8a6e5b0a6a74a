"""The client's half of pre-shared-key authentication (docs/security.md).

Where the key comes from: ``Bridge.connect(security=Psk(key=...))`` (hex, or the key's
bytes), ``Psk(file=...)`` (the key file format ``rlbridge serve --psk-file`` reads: the line of
this client's name, else the default line), else the ``RLBRIDGE_PSK`` environment variable
(hex). ``Tls(psk=Psk(...))`` runs the same handshake inside TLS.
A client given a key insists on authentication: a server that answers the hello without a
challenge (no key configured, or someone in the middle stripping it) is refused, so a key can
never silently downgrade to a session anyone could spoof. Once the server has proven the key
and accepted ours, every datagram both ways and (without TLS) the TCP stream are sealed with
the derived session keys.
"""

from __future__ import annotations

import contextlib
import os
import socket
from collections.abc import Callable, Mapping
from pathlib import Path

from rlbridge import keyfile
from rlbridge.errors import AuthRefused, ConnectionFailed, RemoteProtocolError
from rlbridge.wire import (
    AuthChallenge,
    AuthProof,
    ConnectAck,
    ConnectError,
    Disconnect,
    ErrorCode,
    Packet,
)
from rlbridge.wire.auth import (
    MIN_KEY_SIZE,
    NONCE_SIZE,
    PSK_ENV,
    ClientHandshake,
    SealedCodec,
    SessionKeys,
    parse_key,
    sealed_codec,
)
from rlbridge.wire.codec import FLAG_MAC, PacketCodec, peek_header

_AUTH_CODES = (ErrorCode.AUTH_FAILED, ErrorCode.NOT_ALLOWED)


def resolve_key(psk: bytes | str | None = None, psk_file: str | Path | None = None,
                environ: Mapping[str, str] | None = None, name: str | None = None
                ) -> bytes | None:
    """The key to authenticate with, from the first source that has one (module docstring).

    ``psk`` (``Psk.key``) is the key in hex (``openssl rand -hex 32``), as in the key file and
    ``$RLBRIDGE_PSK``; ``bytes`` are taken as the key itself. ``psk_file`` (``Psk.file``) is
    a key file in the server's format: the line of client ``name``, else the default line.
    ``environ`` defaults to ``os.environ`` (tests pass their own mapping).
    """
    if isinstance(psk, str):
        return parse_key(psk, "Psk(key=...)")
    if psk is not None:
        if len(psk) < MIN_KEY_SIZE:
            raise ValueError(f"Psk(key=...) of {len(psk)} bytes is too short; use at least "
                             f"{MIN_KEY_SIZE} random bytes")
        return bytes(psk)
    if psk_file is not None:
        path = Path(psk_file)
        key = keyfile.key_for(keyfile.parse(keyfile.read(path), str(path)), name or "")
        if key is None:
            raise ValueError(f"{path}: no key for client name {name!r} and no default key")
        return key
    env = (os.environ if environ is None else environ).get(PSK_ENV)
    return parse_key(env, f"${PSK_ENV}") if env else None


class ClientAuth:
    """One connection attempt: a fresh nonce, the answer to the challenge, the sealed codec."""

    def __init__(self, key: bytes, name: str, nonce: bytes | None = None) -> None:
        self._handshake = ClientHandshake(key, name, nonce or os.urandom(NONCE_SIZE))
        self._codec: SealedCodec | None = None

    @property
    def keys(self) -> SessionKeys | None:
        """The session's keys, once the server's challenge was answered."""
        return self._handshake.keys

    @property
    def nonce(self) -> bytes:
        """What the hello carries in its ``auth`` field."""
        return self._handshake.nonce

    def answer(self, challenge: AuthChallenge,
               sock: socket.socket | Callable[[Packet], object]) -> AuthProof:
        """Our proof; raises :class:`AuthRefused` if the server does not know the key.

        Before raising, a ``Disconnect(AUTH_FAILED)`` goes to the server over ``sock`` (the
        handshake's UDP socket, or a function sending a packet on the TCP connection, TLS
        or not), so it can count and log the refusal: the client refuses first, and never
        sends a proof to a server that has not proven the key.
        """
        try:
            proof = self._handshake.answer(challenge)
        except RemoteProtocolError as exc:
            goodbye = Disconnect(int(ErrorCode.AUTH_FAILED), "client refused the server's "
                                 "proof: the two sides have different keys")
            codec = PacketCodec()
            with contextlib.suppress(OSError):
                if not isinstance(sock, socket.socket):
                    sock(goodbye)
                elif sock.type == socket.SOCK_STREAM:
                    sock.sendall(codec.encode_frame(goodbye))
                else:
                    sock.send(codec.encode_datagram(goodbye, 0))
            raise AuthRefused(int(exc.code), exc.reason) from None
        assert self._handshake.keys is not None
        if self._codec is None:
            self._codec = sealed_codec(self._handshake.keys, server=False)
        return proof

    def decode(self, plain: PacketCodec, data: bytes) -> Packet:
        """A handshake datagram: the challenge comes unsealed, the ack sealed (it holds the
        token, so it must come from the server that proved the key)."""
        flags, _token = peek_header(data)
        codec = self._codec if self._codec is not None and flags & FLAG_MAC else plain
        return codec.decode_datagram(data)[2]

    def sealed(self, ack: ConnectAck) -> SealedCodec:
        """The codec of the session ``ack`` opened; refuses a session opened without a proof."""
        if self._codec is None:
            raise AuthRefused(
                int(ErrorCode.AUTH_FAILED),
                f"server accepted session {ack.session} without authenticating; a key was "
                "given, so an unauthenticated server is refused (configure the server's "
                "--psk-file / RLBRIDGE_PSK, or connect without a key)")
        return self._codec


def refused(packet: ConnectError) -> ConnectionFailed:
    """The exception a ConnectError becomes: :class:`AuthRefused` for auth and network."""
    if packet.code in _AUTH_CODES:
        return AuthRefused(packet.code, f"server refused the session: {packet.reason}")
    return ConnectionFailed(f"server refused the session: {packet.reason}")
