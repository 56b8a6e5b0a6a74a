"""Service calls and provided services on the client side of one connection.

A call (``Bridge.call``) sends a ``ServiceCall`` and waits on an event until the receive
thread hands over its ``ServiceResult``; an error code becomes the exception of
:func:`rlbridge.wire.error_from_code` (``NoServiceError``, ``ServiceTimeout``, ...). The
server gives up after the call's timeout; this side waits that long plus the connection's
own timeout for the answer to travel.

A provided service (``Bridge.serve_service``) is a channel of :class:`IncomingRequest`: the
receive thread writes each ``ServiceRequest`` into it, the provider reads one, computes, and
answers with :meth:`IncomingRequest.reply` (or :meth:`~IncomingRequest.fail`). A session that
ends fails the calls in flight with :class:`ConnectionClosed`; requests read but not answered
when it ended cannot be answered any more (their reply raises it too).
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from rlbridge.csp.channel import Channel
from rlbridge.errors import ConnectionClosed, ServiceTimeout
from rlbridge.wire import (
    ErrorCode,
    GoalResult,
    LocalProtocolError,
    ServiceCall,
    ServiceReply,
    ServiceRequest,
    ServiceResult,
    error_from_code,
)

if TYPE_CHECKING:
    from rlbridge.client.session.actions import Goal
    from rlbridge.client.session.session_owner import SessionOwner

#: Requests a provided service's channel holds before the oldest is overwritten (and
#: counted); the server keeps at most as many waiting per service.
REQUEST_BUFFER = 256


@dataclass
class _Call:
    done: threading.Event = field(default_factory=threading.Event)
    answer: ServiceResult | None = None


class IncomingRequest:
    """One request to a service this client provides: ``data``, then ``reply(response)``."""

    __slots__ = ("_answered", "_calls", "_channel", "_generation", "data", "request_id")

    def __init__(self, calls: ServiceCalls, channel: int, generation: int,
                 packet: ServiceRequest) -> None:
        self._calls = calls
        self._channel = channel
        self._generation = generation
        self._answered = False
        #: The request's fields, as a dict.
        self.data: dict[str, Any] = packet.request
        self.request_id = packet.request_id

    def reply(self, response: dict[str, Any]) -> None:
        """Answer with ``response`` (a dict of the response type's fields), once."""
        self._send(ServiceReply(self._channel, self.request_id, 0, dict(response)))

    def fail(self, reason: str) -> None:
        """Tell the caller this request failed (``ServiceFailed`` on an rlbridge caller)."""
        self._send(ServiceReply(self._channel, self.request_id, int(ErrorCode.SERVICE_FAILED),
                                None, reason))

    def _send(self, packet: ServiceReply) -> None:
        if self._answered:
            raise LocalProtocolError(f"request {self.request_id} is already answered")
        self._calls.send_reply(packet, self._generation)
        self._answered = True

    def __repr__(self) -> str:
        return f"IncomingRequest({self.request_id}, {self.data!r})"


class ServiceRequests(Channel[IncomingRequest]):
    """The requests to a service this client provides; ``close()`` withdraws the service."""

    __slots__ = ("_on_close", "channel_id", "service", "srv_type")

    def __init__(self, channel_id: int, service: str, srv_type: str) -> None:
        super().__init__(REQUEST_BUFFER, name=f"{service} [{srv_type}] requests")
        self.channel_id = channel_id
        self.service = service
        self.srv_type = srv_type
        self._on_close: Callable[[], None] | None = None

    def close(self) -> None:
        super().close()
        on_close, self._on_close = self._on_close, None
        if on_close is not None:
            on_close()


class ServiceCalls:
    """The connection's calls in flight and its provided services' channels."""

    def __init__(self, conn: SessionOwner) -> None:
        self._conn = conn
        self._ids = itertools.count(1)
        self._calls: dict[int, _Call] = {}
        self._served: dict[int, ServiceRequests] = {}
        #: Channels of service clients (``Bridge.service_client``): closed with the bridge.
        self.clients: list[Channel[Any]] = []
        #: Action goals running, by channel (``Bridge.send_goal``).
        self.goals: dict[int, Goal] = {}
        self.lock = threading.Lock()

    @property
    def waiting(self) -> bool:
        """A call or a goal waits for its answer (a spinning receive thread spins for it)."""
        return bool(self._calls or self.goals)

    def call(self, service: str, srv_type: str, request: dict[str, Any],
             timeout: float) -> dict[str, Any]:
        """See :meth:`rlbridge.client.bridge.Bridge.call`."""
        conn = self._conn
        if timeout <= 0:
            raise ValueError(f"a service call needs a timeout > 0 s, not {timeout}")
        if not isinstance(request, dict):
            raise TypeError(f"a service request is a dict of fields, not {type(request).__name__}")
        call_id = next(self._ids) & 0xFFFF_FFFF
        pending = _Call()
        with self.lock:
            self._calls[call_id] = pending
        try:
            if not conn.wait_up(min(timeout, conn.timeout)):  # reconnecting: wait a little
                raise ConnectionClosed(f"no session with the server: {conn.close_reason}")
            conn.send_control(ServiceCall(call_id, service, srv_type, request,
                                          max(1, round(timeout * 1000))))
            if not pending.done.wait(timeout + conn.timeout):  # the answer itself was lost
                raise ServiceTimeout(int(ErrorCode.TIMEOUT), f"no answer from the server to "
                                     f"the call of {service} within {timeout + conn.timeout:g} s")
        finally:
            with self.lock:
                self._calls.pop(call_id, None)
        answer = pending.answer
        if answer is None:
            raise ConnectionClosed(f"session ended during the call of {service}: "
                                   f"{conn.close_reason}")
        if answer.code != 0:
            raise error_from_code(answer.code, answer.reason)
        return answer.response or {}

    def on_result(self, packet: ServiceResult) -> None:
        """Receive thread: the answer to a call; wake its caller."""
        with self.lock:
            pending = self._calls.get(packet.call)
        if pending is not None:
            pending.answer = packet
            pending.done.set()

    def add_served(self, requests: ServiceRequests) -> None:
        with self.lock:
            self._served[requests.channel_id] = requests

    def forget_served(self, channel: int) -> None:
        with self.lock:
            self._served.pop(channel, None)

    def on_request(self, packet: ServiceRequest) -> None:
        """Receive thread: a request to a provided service; into its channel."""
        with self.lock:
            requests = self._served.get(packet.channel)
        if requests is not None and not requests.closed:
            requests.write(IncomingRequest(self, packet.channel, self._conn.generation, packet))

    def on_goal_result(self, packet: GoalResult) -> None:
        """Receive thread: a goal ended."""
        with self.lock:
            goal = self.goals.pop(packet.channel, None)
        if goal is not None:
            goal.finish(packet)

    def send_reply(self, packet: ServiceReply, generation: int) -> None:
        conn = self._conn
        if generation != conn.generation or not conn.up:
            raise ConnectionClosed("the session this request came in has ended; "
                                   "its caller no longer waits")
        conn.send_control(packet)

    def session_ended(self, final: bool) -> None:
        """Wake every call in flight (it fails); for good, close the request channels."""
        with self.lock:
            calls = list(self._calls.values())
            goals, self.goals = list(self.goals.values()), {}
            served: list[Channel[Any]] = [*self._served.values(), *self.clients] if final else []
            if final:
                self._served.clear()
                self.clients.clear()
        for pending in calls:
            pending.done.set()
        for goal in goals:
            goal.finish(None)
        for channel in served:
            channel.close()
