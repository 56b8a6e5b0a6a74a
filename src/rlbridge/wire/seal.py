"""Sealing with an AEAD, sans-IO: session keys, sealed datagrams, sealed TCP records.

Theory of operation (docs/protocol.md section 16 is normative, with test vectors). A session
that has a secret seals what it sends with ChaCha20-Poly1305 (libsodium's or cryptography's:
:mod:`rlbridge.wire.aead`): encrypted *and* authenticated,
so a value can be neither read nor forged nor altered on the way. ChaCha20-Poly1305 rather
than AES-GCM because control boards often lack AES instructions (a Raspberry Pi 4 does), where
it is the faster and the constant-time one; on a PC the two differ by a fraction of a
microsecond per datagram, small next to the rest of the datagram's path.

Keys. :func:`derive_keys` expands a secret with HKDF-SHA256 into four 32-byte keys: datagrams
client->server and server->client, TCP records client->server and server->client. One key per
direction means a datagram or record reflected back at its sender does not open. The secret is
the pre-shared key (salt: both handshake nonces, context: the handshake transcript), or, on a
TLS connection, 32 random bytes the server hands the client inside TLS (``ConnectAck``).

Datagrams: ``header(12, flag SEALED) | counter u64 | ciphertext | tag(16)``, nonce = 4 zero
bytes + the counter, associated data = header + counter. The counter starts at 1 and grows by
one per datagram, so a nonce is never used twice under a key; the receiver keeps a
``REPLAY_WINDOW`` sliding window of counters, so a datagram repeated or older than the window
is refused even though it opens.

TCP records use the stream keys the same way (:mod:`rlbridge.wire.records`).
"""

from __future__ import annotations

import itertools
import struct
from dataclasses import dataclass

import msgspec
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from rlbridge.errors import ErrorCode, RemoteProtocolError
from rlbridge.wire.aead import NONCE, InvalidTag, chacha20_poly1305
from rlbridge.wire.codec import (
    FLAG_MAC,
    MAGIC,
    PacketCodec,
    check_header,
)
from rlbridge.wire.packets import PROTOCOL_VERSION, Packet

#: Header flag of a sealed datagram or TCP record (the same bit the MAC-only seal used).
FLAG_SEALED = FLAG_MAC
KEY_SIZE = 32
TAG_SIZE = 16
COUNTER = struct.Struct(">Q")
#: Bytes a sealed datagram carries beyond an unsealed one.
SEAL_OVERHEAD = COUNTER.size + TAG_SIZE
#: Counters remembered behind the highest one seen (IPsec uses 32-1024; reordering here is
#: a burst of a few datagrams, plus redundancy copies).
REPLAY_WINDOW = 1024
_KEYS_LABEL = b"rlbridge-keys-v1\x00"
#: Header and counter of a sealed datagram in one ``pack`` (the hot path: one call, not two).
_SEALED_HEAD = struct.Struct(">2sBBQQ")
#: Where the ciphertext of a sealed datagram starts (header and counter before it).
_OPENS_FROM = _SEALED_HEAD.size
#: What msgspec raises for a body that is not a valid packet (PacketCodec._decode's list).
_DECODE_ERRORS = (msgspec.ValidationError, msgspec.DecodeError, UnicodeDecodeError,
                  RecursionError)


@dataclass(frozen=True, slots=True)
class SessionKeys:
    """The directional keys of one sealed session: datagrams, and TCP records."""

    client_to_server: bytes
    server_to_client: bytes
    stream_client_to_server: bytes
    stream_server_to_client: bytes


def derive_keys(secret: bytes, salt: bytes, context: bytes) -> SessionKeys:
    """HKDF-SHA256(secret, salt, "rlbridge-keys-v1\\0" | context) -> four 32-byte keys."""
    okm = HKDF(hashes.SHA256(), 4 * KEY_SIZE, salt, _KEYS_LABEL + context).derive(secret)
    return SessionKeys(*(okm[i:i + KEY_SIZE] for i in range(0, 4 * KEY_SIZE, KEY_SIZE)))


def tls_datagram_keys(secret: bytes, token: int) -> SessionKeys:
    """The keys of a TLS session's datagrams, from the secret its ``ConnectAck`` carried."""
    return derive_keys(secret, b"", b"tls\x00" + COUNTER.pack(token))


def nonce(counter: int) -> bytes:
    return NONCE.pack(counter)


class DatagramRejected(RemoteProtocolError):
    """A datagram refused by the seal; ``kind`` names the counter it is dropped under."""

    def __init__(self, kind: str, reason: str) -> None:
        super().__init__(ErrorCode.AUTH_FAILED, reason)
        self.kind = kind


class ReplayWindow:
    """Which counters were already accepted, among the ``size`` behind the highest one seen.

    A ring of ``size`` slots (RFC 6479's idea, without the bitmap): slot ``c % size`` holds the
    last counter accepted there. A counter within the window was accepted iff its slot holds
    it: any other counter of that slot differs by a multiple of ``size``, and one that was
    overwritten by a later counter is older than the window anyway. So a check is one list
    read and, if new, one write: no shifting of a ``size``-bit integer per datagram.
    """

    def __init__(self, size: int = REPLAY_WINDOW) -> None:
        self._size = size
        self._top = 0
        self._slots = [0] * size  # 0: no counter (0 is never accepted)

    def check(self, counter: int) -> bool:
        """True if ``counter`` is new (and now remembered); False if repeated or too old."""
        top = self._top
        if counter > top:
            self._top = counter
        elif counter == 0 or top - counter >= self._size:
            return False
        slot = counter % self._size
        slots = self._slots
        if slots[slot] == counter:
            return False
        slots[slot] = counter
        return True


class SealedCodec(PacketCodec):
    """A :class:`PacketCodec` whose datagrams are sealed (frames go through records instead).

    One per session and side: ``send_key`` seals, ``receive_key`` opens. Every datagram must
    be sealed; an unsealed one, one that does not open and a replayed counter raise
    :class:`DatagramRejected`. The counter is an ``itertools.count``, whose ``next`` is atomic
    under the GIL, so the client's threads may seal concurrently.
    """

    def __init__(self, send_key: bytes, receive_key: bytes) -> None:
        super().__init__()
        self._seal = chacha20_poly1305(send_key).seal_counted
        self._open = chacha20_poly1305(receive_key).open_counted
        self._counter = itertools.count(1)
        self.window = ReplayWindow()

    def encode_datagram(self, packet: Packet, token: int, flags: int = 0) -> bytes:
        return self.seal_body(self._encoder.encode(packet), token, flags)

    def seal_body(self, body: bytes, token: int, flags: int = 0) -> bytes:
        """A sealed datagram around ``body`` (encoded packet bytes, or anything: fuzzing)."""
        counter = next(self._counter)
        return self._seal(counter, _SEALED_HEAD.pack(MAGIC, PROTOCOL_VERSION,
                                                     flags | FLAG_SEALED, token, counter), body)

    def decode_datagram(self, data: bytes) -> tuple[int, int, Packet]:
        # The hot path of every sealed datagram on both ends: one unpack for header and
        # counter, the body decoded by msgspec directly (decode_body only for an error).
        if len(data) < _OPENS_FROM + TAG_SIZE:
            raise DatagramRejected("unsealed", f"datagram of {len(data)} bytes is too short "
                                   "to be sealed")
        magic, version, flags, token, counter = _SEALED_HEAD.unpack_from(data)
        if magic != MAGIC or version != PROTOCOL_VERSION:
            check_header(magic, version)
        if not flags & FLAG_SEALED:
            raise DatagramRejected("unsealed", "unsealed datagram on a sealed session")
        try:
            body = self._open(data, _OPENS_FROM, counter)
        except InvalidTag:
            raise DatagramRejected("bad_mac", "datagram does not open under this session's "
                                   "key (forged, altered, or another session's)") from None
        if not self.window.check(counter):
            raise DatagramRejected("replayed", f"datagram counter {counter} was already "
                                   "seen or is older than the replay window")
        try:
            return flags, token, self._decoder.decode(body)
        except _DECODE_ERRORS:
            pass
        try:  # again, for the error decode_body makes of it (tag, channel, bundle parts)
            return flags, token, self.decode_body(body)
        except RemoteProtocolError as exc:
            exc.token = token
            raise


def sealed_codec(keys: SessionKeys, *, server: bool) -> SealedCodec:
    """The codec one side of a sealed session seals and opens datagrams with."""
    if server:
        return SealedCodec(keys.server_to_client, keys.client_to_server)
    return SealedCodec(keys.client_to_server, keys.server_to_client)
