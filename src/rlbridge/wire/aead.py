"""Which ChaCha20-Poly1305 seals this process's datagrams and records: libsodium's, or
cryptography's.

Both implement the same construction (RFC 8439 section 2.8), so the bytes are the same and
either end may use either; docs/protocol.md section 16's test vectors pass with both. What
differs is the cost of one call when the caches are cold, which is every call on a 1 kHz
control stream: `cryptography` copies a fresh OpenSSL context per call and sets nonce, data
and tag through OpenSSL's parameter calls, libsodium is one function call
(docs/benchmarks.md, "Cost of encryption", has both figures). So the package prefers
libsodium, through ``rlbridge.wire._chacha``, a small C extension that setup.py builds when
libsodium's headers are there (Debian: ``apt install libsodium-dev``), and falls back to
`cryptography` (always installed) when it was not built. :data:`STATE` says which this
process uses; ``rlbridge --version`` prints it.

``$RLBRIDGE_AEAD`` chooses for a process: ``cryptography`` (the fallback, e.g. for an A/B
measurement or a test that both interoperate), ``libsodium`` (refuse to start without the
extension), unset or empty: libsodium if built. ``$RLBRIDGE_PURE_PYTHON`` (no compiled code
at all, ``rlbridge._compiled``) implies ``cryptography``.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Callable, Mapping
from typing import Protocol

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305 as _OpenSSLChaCha

from rlbridge._compiled import pure_requested
from rlbridge.errors import NoCipher

#: Chooses the implementation for a process (module docstring).
AEAD_ENV = "RLBRIDGE_AEAD"
LIBSODIUM = "libsodium"
CRYPTOGRAPHY = "cryptography"

__all__ = ["AEAD_ENV", "BULK_FROM", "CRYPTOGRAPHY", "IMPLEMENTATIONS", "LIBSODIUM", "NONCE",
           "STATE", "Aead", "CryptographyChaCha", "InvalidTag", "NoCipher",
           "bulk_chacha20_poly1305", "chacha20_poly1305", "require"]


#: What encrypt and decrypt take as data and associated data (both implementations take any
#: contiguous buffer).
_Data = bytes | bytearray | memoryview


#: Messages from this size on are sealed by :func:`bulk_chacha20_poly1305` where the caller
#: sees both sizes (TCP records). Measured warm on x86-64 with AVX-512: libsodium 1.3 us and
#: cryptography 1.4 us at 1300 bytes, 2.9 and 2.0 us at 4096, 43 and 19 us at 64 KiB.
BULK_FROM = 2048
#: The nonce of a record or datagram counter: 4 zero bytes, then the counter (u64 big-endian).
NONCE = struct.Struct(">4xQ")


class Aead(Protocol):
    """A ChaCha20-Poly1305 under one key: ``decrypt`` and ``open_counted`` raise
    :class:`InvalidTag` for data that does not verify (both implementations raise
    cryptography's class).

    ``seal_counted`` and ``open_counted`` are what sealed datagrams and records do (docs/
    protocol.md section 16): the nonce made from a counter (:data:`NONCE`), the associated
    data the bytes in front of the ciphertext, so one call makes or opens the whole message.
    """

    def encrypt(self, nonce: bytes, data: _Data, associated_data: _Data | None, /) -> bytes:
        ...

    def decrypt(self, nonce: bytes, data: _Data, associated_data: _Data | None, /) -> bytes:
        ...

    def seal_counted(self, counter: int, head: _Data, body: _Data, /) -> bytes:
        """``head + ciphertext + tag`` of ``body``, ``head`` the associated data."""
        ...

    def open_counted(self, data: _Data, head_size: int, counter: int, /) -> bytes:
        """The plaintext of ``data[head_size:]``, ``data[:head_size]`` the associated data."""
        ...


class CryptographyChaCha:
    """cryptography's ChaCha20Poly1305 with :class:`Aead`'s counted calls (what the C
    extension does in one call, here in a few)."""

    def __init__(self, key: bytes) -> None:
        cipher = _OpenSSLChaCha(key)
        self.encrypt = cipher.encrypt
        self.decrypt = cipher.decrypt

    def seal_counted(self, counter: int, head: _Data, body: _Data, /) -> bytes:
        return bytes(head) + self.encrypt(_counter_nonce(counter), body, head)

    def open_counted(self, data: _Data, head_size: int, counter: int, /) -> bytes:
        view = memoryview(data)
        if head_size < 0:
            raise ValueError("head_size must not be negative")
        return self.decrypt(_counter_nonce(counter), view[head_size:], view[:head_size])


def _counter_nonce(counter: int) -> bytes:
    """:data:`NONCE` of ``counter``; OverflowError outside u64, as the C extension says."""
    try:
        return NONCE.pack(counter)
    except struct.error:
        if isinstance(counter, int):
            raise OverflowError(f"counter {counter} is not a u64") from None
        raise TypeError(f"counter must be an int, not {type(counter).__name__}") from None


def _available() -> dict[str, Callable[[bytes], Aead]]:
    found: dict[str, Callable[[bytes], Aead]] = {}
    try:
        from rlbridge.wire._chacha import ChaCha20Poly1305 as _SodiumChaCha
    except ImportError:
        pass
    else:
        found[LIBSODIUM] = _SodiumChaCha
    found[CRYPTOGRAPHY] = CryptographyChaCha
    return found


#: The implementations importable here, preferred first: tests run every one of them.
IMPLEMENTATIONS: Mapping[str, Callable[[bytes], Aead]] = _available()


def choose(environ: Mapping[str, str],
           available: Mapping[str, Callable[[bytes], Aead]]) -> tuple[str | None, str]:
    """``(implementation, why)`` for a process with this environment; the implementation is
    None when ``$RLBRIDGE_AEAD`` asks for what cannot be had (``why`` says what is wrong)."""
    wanted = environ.get(AEAD_ENV, "")
    if wanted not in ("", LIBSODIUM, CRYPTOGRAPHY):
        return None, (f"none: ${AEAD_ENV}={wanted!r} is not {LIBSODIUM!r} or "
                      f"{CRYPTOGRAPHY!r} (unset it to choose the best available)")
    if wanted == LIBSODIUM and LIBSODIUM not in available:
        return None, (f"none: ${AEAD_ENV}=libsodium, but rlbridge.wire._chacha was not "
                      "built (apt install libsodium-dev, then install rlbridge-sdk again)")
    if pure_requested(environ):
        return CRYPTOGRAPHY, "cryptography (RLBRIDGE_PURE_PYTHON is set)"
    if wanted == CRYPTOGRAPHY:
        return CRYPTOGRAPHY, f"cryptography (${AEAD_ENV}=cryptography)"
    if LIBSODIUM in available:
        from rlbridge.wire._chacha import LIBSODIUM_VERSION

        return LIBSODIUM, f"libsodium {LIBSODIUM_VERSION} (C extension)"
    return CRYPTOGRAPHY, ("cryptography (the libsodium extension was not built: "
                          "apt install libsodium-dev, then pip install again)")


_CHOSEN, STATE = choose(os.environ, IMPLEMENTATIONS)


def require() -> None:
    """Raise :class:`NoCipher` unless this process can seal (a server checks at start)."""
    if _CHOSEN is None:
        raise NoCipher(f"no ChaCha20-Poly1305 to seal with: {STATE.removeprefix('none: ')}")


def bulk_chacha20_poly1305(key: bytes) -> Aead:
    """``cryptography``'s ChaCha20-Poly1305 under ``key``, for messages of :data:`BULK_FROM`
    bytes or more (big TCP records): OpenSSL's vectorised ChaCha20 outruns libsodium's
    there, once the per-call set-up is small next to the message (docs/security.md, "Cost of
    sealing"). The same bytes as :func:`chacha20_poly1305`'s."""
    require()
    return CryptographyChaCha(key)


def chacha20_poly1305(key: bytes) -> Aead:
    """This process's ChaCha20-Poly1305 under ``key`` (32 bytes); :class:`NoCipher` if none."""
    require()  # a session that must seal cannot start: say why
    assert _CHOSEN is not None
    return IMPLEMENTATIONS[_CHOSEN](key)
