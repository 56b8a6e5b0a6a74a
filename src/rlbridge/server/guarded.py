"""A TCP transport whose bytes are transformed on the way out (TLS, or sealed records).

The sinks and the session write frames to an ``asyncio.Transport`` and never learn whether the
connection is protected: :class:`GuardedTransport` hands them the same interface and applies the
connection's ``protect`` function (TLS encryption, or the pre-shared-key record sealing) to
every write, in the order of the writes, which is what a record sequence number needs.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any


class GuardedTransport(asyncio.Transport):
    """``inner`` with every write passed through ``protect`` first."""

    @staticmethod
    def plain(data: bytes | bytearray | memoryview) -> bytes:
        """No transformation (a keyed connection before its handshake ends)."""
        return bytes(data)

    def __init__(self, inner: asyncio.Transport,
                 protect: Callable[[bytes | bytearray | memoryview], bytes]) -> None:
        super().__init__()
        self._inner = inner
        self._protect = protect

    def protect_with(self, protect: Callable[[bytes | bytearray | memoryview], bytes]) -> None:
        """Transform later writes with ``protect`` (the handshake is over: keys exist)."""
        self._protect = protect

    def write(self, data: bytes | bytearray | memoryview) -> None:
        if data and not self._inner.is_closing():
            self._inner.write(self._protect(data))

    def is_closing(self) -> bool:
        return self._inner.is_closing()

    def close(self) -> None:
        self._inner.close()

    def abort(self) -> None:
        self._inner.abort()

    def get_write_buffer_size(self) -> int:
        return self._inner.get_write_buffer_size()

    def set_write_buffer_limits(self, high: int | None = None, low: int | None = None) -> None:
        self._inner.set_write_buffer_limits(high, low)

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return self._inner.get_extra_info(name, default)

    def pause_reading(self) -> None:
        self._inner.pause_reading()

    def resume_reading(self) -> None:
        self._inner.resume_reading()

    def is_reading(self) -> bool:
        return self._inner.is_reading()
