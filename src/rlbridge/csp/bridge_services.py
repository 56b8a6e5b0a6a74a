"""The Bridge's requests to the server (a mixin of :class:`~.bridge.Bridge`): service calls
and provided services, parameters, actions, and the server's statistics.

Services are request/response, not streams: a call is a control packet and an answer
(:mod:`rlbridge.csp.services`), made from a soft-real-time thread that may block. A
hard-real-time loop uses :meth:`ServiceMethods.service_client` instead: it writes requests to
a channel and reads responses from another, and a thread of the client makes the calls.
Parameters are calls to a node's ``rcl_interfaces`` services (:mod:`rlbridge.csp.parameters`).
"""

from __future__ import annotations

import contextlib
import itertools
import threading
from typing import TYPE_CHECKING, Any, NamedTuple

from rlbridge.csp import parameters
from rlbridge.csp.actions import Goal
from rlbridge.csp.bridge_channels import IncomingChannel, OutgoingChannel
from rlbridge.csp.channel import Channel
from rlbridge.csp.services import IncomingRequest, ServiceRequests
from rlbridge.errors import ChannelClosed, ConnectionClosed, ParameterError
from rlbridge.wire import GoalSend, RlbridgeError, ServiceOffer, TopicClose

if TYPE_CHECKING:
    from rlbridge.csp.connection import Connection

__all__ = ["CallResult", "IncomingRequest", "ServiceClient", "ServiceMethods",
           "ServiceRequests"]

#: How long a service call waits for its answer unless told otherwise (seconds).
DEFAULT_TIMEOUT = 5.0


class CallResult(NamedTuple):
    """What a :class:`ServiceClient` answers: the request, and its response or error."""

    request: dict[str, Any]
    response: dict[str, Any] | None
    error: RlbridgeError | None


class ServiceClient:
    """Non-blocking service calls: write requests, read :class:`CallResult` later.

    ``requests`` and ``responses`` are buffered channels (a write never blocks; a full
    buffer drops its oldest entry and counts it). One thread of the client takes each request
    in turn and makes the call, so responses come in request order.
    """

    def __init__(self, methods: ServiceMethods, service: str, srv_type: str, *,
                 buffer_size: int, timeout: float) -> None:
        self.service = service
        self.srv_type = srv_type
        self.requests: Channel[dict[str, Any]] = Channel(buffer_size,
                                                         name=f"{service} requests out")
        self.responses: Channel[CallResult] = Channel(buffer_size,
                                                      name=f"{service} responses")
        self._methods = methods
        self._timeout = timeout
        methods._conn.services.clients.append(self.requests)  # closed with the bridge
        self._thread = threading.Thread(target=self._run, name=f"rlbridge-call {service}",
                                        daemon=True)
        self._thread.start()

    def request(self, request: dict[str, Any]) -> None:
        """Queue one request (never blocks)."""
        self.requests.write(request)

    def _run(self) -> None:
        while True:
            try:
                request = self.requests.read()
            except ChannelClosed:
                break
            try:
                response = self._methods.call(self.service, self.srv_type, request,
                                              timeout=self._timeout)
            except RlbridgeError as exc:
                result = CallResult(request, None, exc)
            else:
                result = CallResult(request, response, None)
            with contextlib.suppress(ChannelClosed):
                self.responses.write(result)
        self.responses.close()

    def close(self) -> None:
        """Stop taking requests; a call in progress still finishes (bounded by its timeout)."""
        self.requests.close()
        if self._thread is not threading.current_thread():
            self._thread.join(self._timeout + 10.0)


class ServiceMethods:
    """Services, parameters and actions of a :class:`~rlbridge.csp.bridge.Bridge`."""

    _conn: Connection
    _ids: itertools.count[int]
    _lock: threading.Lock
    _incoming: dict[int, IncomingChannel]
    _outgoing: dict[int, OutgoingChannel]

    # -- services ------------------------------------------------------------------------
    def call(self, service: str, srv_type: str, request: dict[str, Any] | None = None, *,
             timeout: float = DEFAULT_TIMEOUT) -> dict[str, Any]:
        """Call a middleware service and wait for its response (a dict of its fields).

        ``srv_type`` as ``'std_srvs/srv/SetBool'``. Blocks up to ``timeout`` seconds (plus
        the network): for soft-real-time threads; a loop uses :meth:`service_client`.
        Raises ``UnknownTypeError``, ``BadValueError`` (the request does not fit the type),
        ``NoServiceError`` (no server within the timeout), ``ServiceTimeout`` (no answer),
        ``ServiceFailed`` (the server failed), all :class:`~rlbridge.wire.RemoteError`.
        """
        return self._conn.services.call(service, srv_type, request or {}, timeout)

    def service_client(self, service: str, srv_type: str, *, buffer_size: int = 16,
                       timeout: float = DEFAULT_TIMEOUT) -> ServiceClient:
        """Calls for a loop that must not block: ``client.request(req)`` (or
        ``client.requests.write``), later ``client.responses.try_read()`` -> :class:`CallResult`.
        ``client.close()`` stops it."""
        return ServiceClient(self, service, srv_type, buffer_size=buffer_size, timeout=timeout)

    def serve_service(self, service: str, srv_type: str) -> ServiceRequests:
        """Provide ``service``: a channel of requests; ``req = requests.read(timeout=...)``,
        then ``req.data`` (a dict) and ``req.reply(response_dict)`` (or ``req.fail(reason)``).

        ``requests.close()`` withdraws the service. Raises ``UnknownTypeError`` for an
        unknown type and ``BindingRefused`` when the service is provided already.
        """
        ch_id = next(self._ids)
        requests = ServiceRequests(ch_id, service, srv_type)
        conn = self._conn
        conn.services.add_served(requests)
        try:
            conn.request_topic(ServiceOffer(ch_id, service, srv_type))
        except BaseException:
            conn.services.forget_served(ch_id)
            raise

        def withdraw() -> None:
            conn.services.forget_served(ch_id)
            conn.forget_topic(ch_id)
            if conn.up:
                with contextlib.suppress(OSError, ConnectionClosed):
                    conn.send_control(TopicClose(ch_id))

        requests._on_close = withdraw
        return requests

    def service_list(self) -> list[tuple[str, str]]:
        """The services the server's middleware knows, as ``(name, type)``."""
        body = self._conn.request_stats({"services": True})
        found: Any = body.get("services", [])
        return [(str(n), str(t)) for n, t in found]

    # -- actions -----------------------------------------------------------------------
    def send_goal(self, action: str, action_type: str, goal: dict[str, Any] | None = None, *,
                  feedback_buffer: int = 1024, timeout: float = DEFAULT_TIMEOUT) -> Goal:
        """Send an action goal; returns once the action server accepted it.

        ``goal.feedback`` is a channel of feedback dicts, ``goal.result(timeout=...)`` waits
        for the result dict (``goal.status``: ``succeeded``, ``canceled``, ``aborted``),
        ``goal.cancel()`` asks for a cancel. Raises ``NoServiceError`` (no action server),
        ``GoalRejected``, ``UnknownTypeError``, ``BadValueError``, ``ServiceTimeout``.
        """
        conn = self._conn
        ch_id = next(self._ids)
        feedback = IncomingChannel(ch_id, action, action_type, None, transport="tcp",
                                   blocking=True, buffer_size=feedback_buffer,
                                   link=conn.link)
        handle = Goal(conn, ch_id, action, feedback)

        def forget() -> None:
            with self._lock:
                self._incoming.pop(ch_id, None)

        handle.on_finish = forget
        with self._lock:
            self._incoming[ch_id] = feedback
        with conn.services.lock:
            conn.services.goals[ch_id] = handle
        try:
            conn.request_topic(GoalSend(ch_id, action, action_type, goal or {},
                                        max(1, round(timeout * 1000))))
        except BaseException:
            with conn.services.lock:
                conn.services.goals.pop(ch_id, None)
            with self._lock:
                self._incoming.pop(ch_id, None)
            raise
        finally:
            conn.forget_topic(ch_id)  # a goal is not sent again after a reconnect
        return handle

    # -- the server's own answers ---------------------------------------------------------
    def _on_ros_loss(self, channel: int, ros_lost: int) -> None:
        """Receive thread: the server counted ROS-side loss of a channel (``health()``)."""
        found: IncomingChannel | OutgoingChannel | None = self._incoming.get(channel)
        if found is None:  # not ``or``: an empty channel is falsy
            found = self._outgoing.get(channel)
        if found is not None:
            found.ros_lost = ros_lost

    # -- parameters --------------------------------------------------------------------
    def get_parameter(self, node: str, name: str, *,
                      timeout: float = DEFAULT_TIMEOUT) -> parameters.ParameterValue:
        """The value of parameter ``name`` of ROS node ``node`` (``ParameterError`` if unset)."""
        answer = self.call(parameters.node_service(node, "get_parameters"), parameters.GET,
                           {"names": [name]}, timeout=timeout)
        values = answer.get("values") or [{}]
        value = parameters.from_ros(values[0])
        if value is None:
            raise ParameterError(f"node {node} has no parameter '{name}'")
        return value

    def set_parameter(self, node: str, name: str, value: Any, *,
                      timeout: float = DEFAULT_TIMEOUT) -> None:
        """Set parameter ``name`` of ``node``; ``ParameterError`` with the node's reason if it
        refuses (undeclared, read-only, wrong type)."""
        answer = self.call(parameters.node_service(node, "set_parameters"), parameters.SET,
                           {"parameters": [{"name": name, "value": parameters.to_ros(value)}]},
                           timeout=timeout)
        result = (answer.get("results") or [{}])[0]
        if not result.get("successful"):
            raise ParameterError(
                f"node {node} refused {name}={value!r}: {result.get('reason') or 'no reason'}")

    def list_parameters(self, node: str, *, timeout: float = DEFAULT_TIMEOUT) -> list[str]:
        """The names of every parameter of ``node``, sorted."""
        answer = self.call(parameters.node_service(node, "list_parameters"), parameters.LIST,
                           {"prefixes": [], "depth": 0}, timeout=timeout)
        return sorted(answer.get("result", {}).get("names", []))
