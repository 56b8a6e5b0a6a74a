"""Service calls for a loop that must not block: requests in one channel, answers in another.

``Bridge.call`` blocks until the answer comes, which a hard-real-time loop cannot afford. A
:class:`ServiceClient` gives such a loop two channels instead: it writes requests into one and
reads :class:`CallResult` values from the other, while a thread of the client makes each
call in turn (:class:`~rlbridge.client.session.services.ServiceCalls.call`).
"""

from __future__ import annotations

import contextlib
import threading
from typing import TYPE_CHECKING, Any, NamedTuple

from rlbridge.csp.channel import Channel
from rlbridge.errors import ChannelClosed
from rlbridge.wire import RlbridgeError

if TYPE_CHECKING:
    from rlbridge.client.session.services import ServiceCalls

__all__ = ["DEFAULT_TIMEOUT", "CallResult", "ServiceClient"]

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

    def __init__(self, calls: ServiceCalls, service: str, srv_type: str, *,
                 buffer_size: int, timeout: float) -> None:
        self.service = service
        self.srv_type = srv_type
        self.requests: Channel[dict[str, Any]] = Channel(buffer_size,
                                                         name=f"{service} requests out")
        self.responses: Channel[CallResult] = Channel(buffer_size,
                                                      name=f"{service} responses")
        self._calls = calls
        self._timeout = timeout
        calls.clients.append(self.requests)  # closed with the bridge
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
                response = self._calls.call(self.service, self.srv_type, request or {},
                                            self._timeout)
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
