"""Control requests of a connection waiting for their answers: topic-connects and stats.

The asking thread (a channel being bound, ``rlbridge stats``) sends the request and waits on an
event; the receive thread (:mod:`rlbridge.client.session.receiver`) hands the answer over with
:meth:`Requests.answer` and sets it. A refusal answers too, so the asker fails at once with the
server's reason instead of waiting out its patience: a ``TopicError`` by its channel, and an
``Error(TOO_LARGE)`` without one (:meth:`Requests.refused`) every stats request, whose answer
did not fit a datagram (protocol.md 12.2). The acknowledged bindings are kept here too: they
are what a new session binds again after a reconnect.
"""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import msgspec

from rlbridge.errors import ConnectionClosed, ConnectionFailed
from rlbridge.wire import (
    Error,
    ErrorCode,
    GoalSend,
    LocalProtocolError,
    Packet,
    ServiceOffer,
    Stats,
    TopicAck,
    TopicConnect,
    TopicError,
    error_from_code,
)

if TYPE_CHECKING:
    from rlbridge.client.session.session_owner import SessionOwner


@dataclass
class _Pending:
    """A control request waiting for its answer from the receive thread."""

    done: threading.Event
    answer: Packet | None = None


class Requests:
    """The requests of one connection that wait for answers, across its sessions."""

    def __init__(self, conn: SessionOwner) -> None:
        self._conn = conn
        self._pending: dict[int, _Pending] = {}
        #: Every binding the server acknowledged, by channel: what a new session binds again.
        self._bindings: dict[int, TopicConnect | ServiceOffer | GoalSend] = {}
        #: Of those, the ones that bring values or requests in (subscriptions, service
        #: offers): a spinning receive thread spins only while there is one (receiver.py).
        self.incoming = 0
        self._stats_waiters: list[_Pending] = []
        self._lock = threading.Lock()

    def topic(self, req: TopicConnect | ServiceOffer | GoalSend) -> TopicAck:
        """See :meth:`rlbridge.client.session.connection.Connection.request_topic`.

        A service offer binds a channel like a topic-connect (and is bound again after a
        reconnect the same way); ``what`` names either in errors.
        """
        conn = self._conn
        what = (f"topic-connect for {req.topic}" if isinstance(req, TopicConnect)
                else f"service offer of {req.service}" if isinstance(req, ServiceOffer)
                else f"goal for {req.action}")
        # A goal's answer waits for the action server (up to its timeout) on the server.
        patience = conn.timeout + (req.timeout_ms / 1000 if isinstance(req, GoalSend) else 0)
        try:  # Structs are not validated when built: check locally, before the network
            msgspec.convert(msgspec.to_builtins(req), type(req))
        except msgspec.ValidationError as exc:
            raise LocalProtocolError(f"invalid {what}: {exc}") from None
        pending = _Pending(threading.Event())
        with self._lock:
            self._pending[req.channel] = pending
        try:
            deadline = time.monotonic() + patience
            while pending.answer is None:
                if conn.closed.is_set():
                    raise ConnectionClosed(f"connection closed: {conn.close_reason}")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ConnectionFailed(
                        f"no answer to the {what} within {patience:g} s")
                if not conn.wait_up(left):
                    continue
                pending.done.clear()
                with contextlib.suppress(OSError, ConnectionClosed):  # session ended: retry
                    conn.send_control(req)
                pending.done.wait(min(left, 0.25 if conn.control == "udp" else left))
        finally:
            with self._lock:
                self._pending.pop(req.channel, None)
        answer = pending.answer
        if isinstance(answer, TopicAck):
            with self._lock:
                self._bindings[req.channel] = req
                self._count_incoming()
            return answer
        if isinstance(answer, TopicError):
            raise error_from_code(answer.code, answer.reason, channel=answer.channel)
        raise ConnectionClosed(f"connection closed: {conn.close_reason}")

    def stats(self, ask: dict[str, object] | None = None) -> dict[str, object]:
        """See :meth:`rlbridge.client.session.connection.Connection.request_stats`."""
        conn = self._conn
        if not conn.wait_up(conn.timeout):
            raise ConnectionFailed(f"no session with the server within {conn.timeout} s: "
                                   f"{conn.close_reason}")
        pending = _Pending(threading.Event())
        with self._lock:
            self._stats_waiters.append(pending)
        conn.send_control(Stats(ask or {}))
        answered = pending.done.wait(conn.timeout)
        answer = pending.answer
        if isinstance(answer, Error):
            raise error_from_code(answer.code, f"statistics refused: {answer.reason}")
        if not answered or not isinstance(answer, Stats):
            raise ConnectionFailed(f"no statistics from the server within {conn.timeout} s")
        return answer.body

    def answer(self, packet: TopicAck | TopicError) -> None:
        """The receive thread got the answer to a topic-connect: wake its asker."""
        with self._lock:
            pending = self._pending.get(packet.channel)
        if pending is not None:
            pending.answer = packet
            pending.done.set()

    def answer_stats(self, packet: Stats | Error) -> None:
        """The receive thread got statistics, or their refusal: every waiting asker gets it."""
        with self._lock:
            waiters, self._stats_waiters = self._stats_waiters, []
        for pending in waiters:
            pending.answer = packet
            pending.done.set()

    def refused(self, error: Error) -> None:
        """The receive thread got an ``Error``: fail the request it answers, if any. Only a
        stats request is refused by an ``Error`` (its answer too large for a datagram, code
        ``TOO_LARGE`` without a channel); other errors concern values or the session."""
        if error.code == ErrorCode.TOO_LARGE and error.channel is None:
            self.answer_stats(error)

    def session_ended(self) -> None:
        """Wake every topic-connect waiting, to ask again in the next session or give up."""
        with self._lock:
            for pending in self._pending.values():
                pending.done.set()

    def bindings(self) -> list[TopicConnect | ServiceOffer | GoalSend]:
        """See :meth:`rlbridge.client.session.connection.Connection.bindings`."""
        with self._lock:
            return list(self._bindings.values())

    def forget(self, channel: int) -> None:
        """See :meth:`rlbridge.client.session.connection.Connection.forget_topic`."""
        with self._lock:
            self._bindings.pop(channel, None)
            self._count_incoming()

    def _count_incoming(self) -> None:
        self.incoming = sum(not isinstance(b, TopicConnect) or b.direction == "subscribe"
                            for b in self._bindings.values())
