"""Both ChaCha20-Poly1305 implementations (rlbridge.wire.aead) are the same function: RFC 8439's
vector, each other's bytes, the same refusals; and the environment picks between them.

``RLBRIDGE_TEST_REQUIRE_COMPILED=1`` (scripts/test.sh installs libsodium-dev, then compiles)
makes a missing libsodium extension a failure instead of a skip.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import pytest
from hypothesis import given
from hypothesis import strategies as st

from rlbridge._compiled import PURE_ENV, pure_requested
from rlbridge.wire import aead
from rlbridge.wire.aead import (
    AEAD_ENV,
    CRYPTOGRAPHY,
    IMPLEMENTATIONS,
    LIBSODIUM,
    NONCE,
    Aead,
    InvalidTag,
    choose,
)

REQUIRE = (os.environ.get("RLBRIDGE_TEST_REQUIRE_COMPILED") == "1"
           and not pure_requested(os.environ))


def _implementations() -> list[object]:
    params: list[object] = [pytest.param(IMPLEMENTATIONS[CRYPTOGRAPHY], id=CRYPTOGRAPHY)]
    if LIBSODIUM in IMPLEMENTATIONS:
        params.insert(0, pytest.param(IMPLEMENTATIONS[LIBSODIUM], id=LIBSODIUM))
    else:  # test_require_compiled_means_libsodium_is_there fails if it had to be built
        params.insert(0, pytest.param(None, id=LIBSODIUM, marks=pytest.mark.skip(
            reason="rlbridge.wire._chacha was not built (no libsodium headers)")))
    return params


IMPL = pytest.mark.parametrize("make", _implementations())
Make = Callable[[bytes], Aead]

# RFC 8439, section 2.8.2.
RFC_KEY = bytes(range(0x80, 0xA0))
RFC_NONCE = bytes.fromhex("070000004041424344454647")
RFC_AAD = bytes.fromhex("50515253c0c1c2c3c4c5c6c7")
RFC_PLAIN = (b"Ladies and Gentlemen of the class of '99: If I could offer you only one tip "
             b"for the future, sunscreen would be it.")
RFC_SEALED = bytes.fromhex(
    "d31a8d34648e60db7b86afbc53ef7ec2a4aded51296e08fea9e2b5a736ee62d63dbea45e8ca96712"
    "82fafb69da92728b1a71de0a9e060b2905d6a5b67ecd3b3692ddbd7f2d778b8c9803aee328091b58"
    "fab324e4fad675945585808b4831d7bc3ff4def08e4b7a9de576d26586cec64b6116"
    "1ae10b594f09e26a7e902ecbd0600691")


def test_require_compiled_means_libsodium_is_there() -> None:
    if REQUIRE:
        assert LIBSODIUM in IMPLEMENTATIONS, (
            "RLBRIDGE_TEST_REQUIRE_COMPILED=1 but rlbridge.wire._chacha was not built; "
            "`pip install -v -e . 2>&1 | grep 'rlbridge build'` says why")
        assert aead.STATE.startswith("libsodium") or os.environ.get(AEAD_ENV), aead.STATE


@IMPL
def test_rfc_8439_vector(make: Make) -> None:
    cipher = make(RFC_KEY)
    assert cipher.encrypt(RFC_NONCE, RFC_PLAIN, RFC_AAD) == RFC_SEALED
    assert cipher.decrypt(RFC_NONCE, RFC_SEALED, RFC_AAD) == RFC_PLAIN


@IMPL
@given(key=st.binary(min_size=32, max_size=32), nonce=st.binary(min_size=12, max_size=12),
       data=st.binary(max_size=2000), aad=st.none() | st.binary(max_size=64),
       flip=st.integers(min_value=0))
def test_the_same_bytes_as_cryptography_and_any_change_is_refused(
        make: Make, key: bytes, nonce: bytes, data: bytes, aad: bytes | None,
        flip: int) -> None:
    reference = IMPLEMENTATIONS[CRYPTOGRAPHY](key)
    cipher = make(key)
    sealed = cipher.encrypt(nonce, data, aad)
    assert sealed == reference.encrypt(nonce, data, aad)
    assert len(sealed) == len(data) + 16
    assert cipher.decrypt(nonce, sealed, aad) == data
    assert reference.decrypt(nonce, sealed, aad) == data
    bit = flip % (8 * len(sealed))
    tampered = bytearray(sealed)
    tampered[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(InvalidTag):
        cipher.decrypt(nonce, bytes(tampered), aad)
    with pytest.raises(InvalidTag):  # truncated: a tag cut short, or data without it
        cipher.decrypt(nonce, sealed[:-1], aad)
    with pytest.raises(InvalidTag):  # other associated data (the header it was sealed with)
        cipher.decrypt(nonce, sealed, (aad or b"") + b"x")


@IMPL
@given(key=st.binary(min_size=32, max_size=32), counter=st.integers(0, 2**64 - 1),
       head=st.binary(max_size=40), body=st.binary(max_size=1500))
def test_counted_calls_are_encrypt_and_decrypt_with_the_counters_nonce(
        make: Make, key: bytes, counter: int, head: bytes, body: bytes) -> None:
    """What sealed datagrams and records call: the same bytes as the generic calls make."""
    cipher, reference = make(key), IMPLEMENTATIONS[CRYPTOGRAPHY](key)
    nonce = NONCE.pack(counter)
    sealed = cipher.seal_counted(counter, head, body)
    assert sealed == head + reference.encrypt(nonce, body, head)
    assert cipher.open_counted(sealed, len(head), counter) == body
    assert reference.open_counted(sealed, len(head), counter) == body
    with pytest.raises(InvalidTag):  # another counter: another nonce
        cipher.open_counted(sealed, len(head), counter ^ 1)
    if head:
        with pytest.raises(InvalidTag):  # a changed head: other associated data
            cipher.open_counted(bytes([head[0] ^ 1]) + sealed[1:], len(head), counter)
    with pytest.raises(InvalidTag):  # too short to hold a tag after the head
        cipher.open_counted(sealed[:len(head) + 15], len(head), counter)


@IMPL
@given(data=st.binary(max_size=200), head_size=st.integers(0, 220),
       counter=st.integers(0, 2**64 - 1))
def test_arbitrary_bytes_never_open(make: Make, data: bytes, head_size: int,
                                    counter: int) -> None:
    """What anyone on the network can send the opener: refused, whatever its shape."""
    with pytest.raises(InvalidTag):
        make(bytes(range(32))).open_counted(data, head_size, counter)


@IMPL
def test_counted_calls_refuse_bad_counters_and_sizes(make: Make) -> None:
    cipher = make(bytes(32))
    for counter in (-1, 2**64):
        with pytest.raises(OverflowError):
            cipher.seal_counted(counter, b"h", b"b")
    with pytest.raises(TypeError):
        cipher.seal_counted("1", b"h", b"b")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="negative"):
        cipher.open_counted(bytes(40), -1, 1)
    with pytest.raises(InvalidTag):  # a head longer than the data
        cipher.open_counted(bytes(20), 30, 1)


@IMPL
def test_buffers_none_and_large_messages(make: Make) -> None:
    """Any contiguous buffer (records pass memoryview slices); no associated data is the same
    as empty; a record over 64 KiB is the same function."""
    key, nonce = bytes(range(32)), bytes(12)
    cipher, reference = make(key), IMPLEMENTATIONS[CRYPTOGRAPHY](key)
    big = os.urandom((1 << 16) + 17)
    for data in (bytearray(b"abc"), memoryview(b"xxabcxx")[2:5], b"abc"):
        assert cipher.encrypt(nonce, data, memoryview(b"h")) == \
            reference.encrypt(nonce, b"abc", b"h")
    assert cipher.encrypt(nonce, b"abc", None) == cipher.encrypt(nonce, b"abc", b"")
    sealed = cipher.encrypt(nonce, big, b"head")
    assert sealed == reference.encrypt(nonce, big, b"head")
    assert cipher.decrypt(nonce, memoryview(sealed), b"head") == big
    assert cipher.encrypt(nonce, b"", None) == reference.encrypt(nonce, b"", None)
    assert cipher.decrypt(nonce, cipher.encrypt(nonce, b"", None), None) == b""


@IMPL
def test_bad_arguments_are_refused_clearly(make: Make) -> None:
    for key in (b"", bytes(31), bytes(33)):
        with pytest.raises(ValueError, match="32 bytes"):
            make(key)
    cipher = make(bytes(32))
    for nonce in (b"", bytes(11), bytes(13)):
        with pytest.raises(ValueError, match="12 bytes"):
            cipher.encrypt(nonce, b"x", None)
        with pytest.raises(ValueError, match="12 bytes"):
            cipher.decrypt(nonce, bytes(16), None)
    with pytest.raises(TypeError):
        cipher.encrypt(bytes(12), "text", None)  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        cipher.encrypt(bytes(12), b"x", 3)  # type: ignore[arg-type]


def test_the_extension_without_a_key_refuses_to_seal() -> None:
    if LIBSODIUM not in IMPLEMENTATIONS:
        pytest.skip("rlbridge.wire._chacha was not built")
    from rlbridge.wire._chacha import ChaCha20Poly1305

    keyless = ChaCha20Poly1305.__new__(ChaCha20Poly1305)
    with pytest.raises(ValueError, match="not given a key"):
        keyless.encrypt(bytes(12), b"x", None)
    with pytest.raises(TypeError, match="3 arguments"):
        ChaCha20Poly1305(bytes(32)).encrypt(bytes(12), b"x")  # type: ignore[call-arg]
    with pytest.raises(TypeError, match=r"seal_counted\(counter, head, body\) takes 3"):
        ChaCha20Poly1305(bytes(32)).seal_counted(1, b"h")  # type: ignore[call-arg]
    with pytest.raises(ValueError, match="not given a key"):
        keyless.open_counted(bytes(40), 0, 1)


@pytest.mark.parametrize(("env", "available", "chosen", "why"), [
    ({}, (LIBSODIUM, CRYPTOGRAPHY), LIBSODIUM, "libsodium"),
    ({}, (CRYPTOGRAPHY,), CRYPTOGRAPHY, "not built"),
    ({AEAD_ENV: "cryptography"}, (LIBSODIUM, CRYPTOGRAPHY), CRYPTOGRAPHY, AEAD_ENV),
    ({PURE_ENV: "1"}, (LIBSODIUM, CRYPTOGRAPHY), CRYPTOGRAPHY, PURE_ENV),
    ({PURE_ENV: "0"}, (LIBSODIUM, CRYPTOGRAPHY), LIBSODIUM, "libsodium"),
    ({AEAD_ENV: "libsodium"}, (CRYPTOGRAPHY,), None, "was not built"),
    ({AEAD_ENV: "aes"}, (LIBSODIUM, CRYPTOGRAPHY), None, "is not 'libsodium'"),
])
def test_the_environment_chooses(env: dict[str, str], available: tuple[str, ...],
                                 chosen: str | None, why: str) -> None:
    if LIBSODIUM in available and LIBSODIUM not in IMPLEMENTATIONS:
        pytest.skip("rlbridge.wire._chacha was not built")
    got, reason = choose(env, {name: IMPLEMENTATIONS[name] for name in available})
    assert got == chosen
    assert why in reason
