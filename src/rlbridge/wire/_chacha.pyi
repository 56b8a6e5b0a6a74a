"""Types of the C extension ``_chacha.c`` (libsodium's ChaCha20-Poly1305; see aead.py)."""

_Data = bytes | bytearray | memoryview

LIBSODIUM_VERSION: str

class ChaCha20Poly1305:
    def __init__(self, key: bytes) -> None: ...
    def encrypt(self, nonce: bytes, data: _Data, associated_data: _Data | None, /) -> bytes:
        ...
    def decrypt(self, nonce: bytes, data: _Data, associated_data: _Data | None, /) -> bytes:
        ...
