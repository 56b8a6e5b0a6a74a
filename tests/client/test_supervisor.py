"""The reconnect supervisor against a scripted connection: no sockets, no server."""

from __future__ import annotations

import threading

from link_helpers import WAIT

from rlbridge import ConnectionFailed
from rlbridge.client.session.reconnect import Backoff, ReconnectSupervisor
from waiting import wait_until


class ScriptedConnection:
    """Ends one session, then fails ``failures`` reopen attempts before one succeeds."""

    def __init__(self, failures: int) -> None:
        self.failures = failures
        self.attempts = 0
        self.reopened = threading.Event()
        self._cond = threading.Condition()
        self._ended = True

    def wait_session_end(self, stop: threading.Event) -> bool:
        with self._cond:
            self._cond.wait_for(lambda: self._ended or stop.is_set())
            return self._ended and not stop.is_set()

    def reopen(self) -> None:
        self.attempts += 1
        if self.attempts <= self.failures:
            raise ConnectionFailed(f"attempt {self.attempts} refused")
        with self._cond:
            self._ended = False
        self.reopened.set()

    def wake(self) -> None:
        with self._cond:
            self._cond.notify_all()


def test_supervisor_retries_with_backoff_then_binds_once() -> None:
    conn = ScriptedConnection(failures=3)
    asked: list[int] = []

    class Recording(Backoff):
        def next_delay(self, attempt: int) -> float:
            asked.append(attempt)
            return 0.001

    bound = threading.Event()
    sup = ReconnectSupervisor(conn, Recording(), bound.set)
    sup.start()
    assert bound.wait(WAIT)
    assert asked == [0, 1, 2, 3]  # one delay before each attempt, growing with failures
    assert sup.failed_attempts == 3
    assert sup.reconnects == 1
    sup.stop()
    assert sup.native_id is None  # joined


def test_stop_ends_a_long_backoff_at_once() -> None:
    conn = ScriptedConnection(failures=1_000)
    sup = ReconnectSupervisor(conn, Backoff(initial=3600.0, max_delay=3600.0),
                              lambda: None)
    sup.start()
    stopper = threading.Thread(target=sup.stop)
    stopper.start()
    stopper.join(WAIT)  # an hour of backoff otherwise
    assert not stopper.is_alive()
    assert conn.attempts == 0


def test_a_failing_rebind_counts_as_a_failed_attempt() -> None:
    conn = ScriptedConnection(failures=0)
    calls: list[int] = []

    def bind() -> None:
        calls.append(1)
        if len(calls) == 1:
            raise ConnectionFailed("the session ended while binding")

    sup = ReconnectSupervisor(conn, Backoff(initial=0.001, max_delay=0.001), bind)
    sup.start()
    try:
        assert conn.reopened.wait(WAIT)
        wait_until(lambda: sup.reconnects, "the second bind", timeout=WAIT)
        assert sup.reconnects == 1
        assert sup.failed_attempts == 1
        assert len(calls) == 2
        assert conn.attempts == 2
    finally:
        sup.stop()
