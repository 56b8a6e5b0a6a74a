"""Reconnect, in three small pieces: the client's state, a backoff policy, a supervisor.

Theory of operation (nats.py's shape, without its single client class). The
:class:`~rlbridge.client.session.connection.Connection` runs one *session* at a time: a handshake,
then a
receive thread that ends when the session does (the server hung up, the socket broke, or the
watchdog heard nothing for the server's ``timeout_ms``). With reconnect on, the end of a session
is not the end of the connection: the :class:`ReconnectSupervisor` thread wakes, waits
``Backoff.next_delay(attempt)`` (growing, jittered, capped), asks the connection for a new
session, and hands it to ``on_session`` (the :class:`~rlbridge.client.bridge.Bridge`), which binds
every channel again under its old id. Until then outgoing values wait in their channels' rings
(their overflow policy and counters apply) and incoming readers keep waiting.

Lifetimes: the Bridge creates and starts the supervisor and stops it in ``close``; stopping sets
one event, which ends a backoff wait at once, and the connection's ``close`` aborts a handshake
in progress, so ``Bridge.close()`` returns promptly in every phase.
"""

from __future__ import annotations

import logging
import random
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from rlbridge._compat import StrEnum
from rlbridge.wire import RlbridgeError

log = logging.getLogger("rlbridge.client")


class ClientState(StrEnum):
    """Where a connection is in its life; only ``CLOSED`` is final."""

    CONNECTING = "connecting"
    CONNECTED = "connected"
    RECONNECTING = "reconnecting"
    CLOSED = "closed"


@dataclass(frozen=True)
class Backoff:
    """Delay before reconnect attempt ``attempt`` (0, 1, ...): a pure function plus jitter.

    ``initial * factor**attempt``, capped at ``max_delay``, then shortened by a random fraction
    of at most ``jitter`` so that many clients of one restarted server do not knock in step.
    ``rand`` is the source of that fraction (``random.random``; give a seeded one in tests).
    """

    initial: float = 0.05
    max_delay: float = 2.0
    factor: float = 2.0
    jitter: float = 0.2
    rand: Callable[[], float] = field(default=random.random, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not 0 < self.initial <= self.max_delay:
            raise ValueError(f"backoff needs 0 < initial <= max_delay, got initial="
                             f"{self.initial} s and max_delay={self.max_delay} s")
        if self.factor < 1:
            raise ValueError(f"backoff factor must be >= 1, got {self.factor}")
        if not 0 <= self.jitter < 1:
            raise ValueError(f"backoff jitter must be in [0, 1), got {self.jitter}")

    def next_delay(self, attempt: int) -> float:
        """Seconds to wait before attempt ``attempt``; never above ``max_delay``."""
        if attempt < 0:
            raise ValueError(f"attempt must be >= 0, got {attempt}")
        # Exponent capped so that a long outage never builds a float overflow.
        base = min(self.max_delay, self.initial * self.factor ** min(attempt, 64))
        return base * (1.0 - self.jitter * self.rand())


class Reopenable(Protocol):
    """What the supervisor needs from a connection."""

    def wait_session_end(self, stop: threading.Event) -> bool:
        """Block until the current session ended (True) or ``stop`` is set (False)."""
        ...

    def reopen(self) -> None:
        """Start a new session; raises on failure, ``ConnectionClosed`` once closed."""
        ...

    def wake(self) -> None:
        """Make :meth:`wait_session_end` re-check its ``stop`` event."""
        ...


class ReconnectSupervisor:
    """Owns the reconnect thread: waits for a session to end, then reopens with backoff."""

    def __init__(self, conn: Reopenable, backoff: Backoff,
                 on_session: Callable[[], None]) -> None:
        self._conn = conn
        self.backoff = backoff
        self._on_session = on_session
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rlbridge-reconnect", daemon=True)
        #: Sessions opened again, and attempts that failed (both only grow).
        self.reconnects = 0
        self.failed_attempts = 0

    def start(self) -> None:
        self._thread.start()

    @property
    def native_id(self) -> int | None:
        """The thread's OS id (for ``Bridge.set_io_priority``), ``None`` when not running."""
        return self._thread.native_id if self._thread.is_alive() else None

    def request_stop(self) -> None:
        """Stop after the current step; a backoff wait ends at once. Does not wait."""
        self._stop.set()
        self._conn.wake()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop and join; the caller closes the connection first to abort a handshake."""
        self.request_stop()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def _run(self) -> None:
        while self._conn.wait_session_end(self._stop):
            attempt = 0
            while not self._stop.wait(self.backoff.next_delay(attempt)):
                try:
                    self._conn.reopen()
                    self._on_session()
                except (RlbridgeError, OSError) as exc:  # refused, unreachable, closed
                    self.failed_attempts += 1
                    attempt += 1
                    log.info("reconnect attempt %d failed: %s", attempt, exc)
                    continue
                self.reconnects += 1
                break
