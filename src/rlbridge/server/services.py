"""A session's service calls and offered services, between its client and the middleware.

Calls. ``adapter.call_service`` blocks (it waits for discovery and for the answer), so each
call runs on a worker thread of the server's pool and its ``ServiceResult`` is sent from the
event loop when it completes. A session has at most :data:`MAX_CALLS` calls in flight; one
more is answered with ``LIMIT`` at once, so a client cannot tie up the pool.

Offers. A client provides a service on a channel of its own (``ServiceOffer``). Each request
the middleware hands over (on any thread) hops to the event loop, gets a request id, and goes
to the client as a ``ServiceRequest``; the client's ``ServiceReply`` completes it. At most
:data:`MAX_PENDING` requests per offer wait for their answer; more fail at once (the provider
is behind), and withdrawing the offer or ending the session fails the ones still open.
"""

from __future__ import annotations

import itertools
import logging
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from rlbridge.adapters.base import BindingError, ServiceReply, ServiceServer
from rlbridge.server.sinks import PacketSink
from rlbridge.server.worker_calls import (
    MAX_TIMEOUT_S,
    Failure,
    channel_in_use,
    error_code,
    off_loop,
    outcome,
    timeout_s,
)
from rlbridge.wire import (
    ErrorCode,
    ServiceCall,
    ServiceOffer,
    ServiceRequest,
    ServiceResult,
    TopicAck,
    TopicError,
)
from rlbridge.wire import (
    ServiceReply as ServiceReplyPacket,
)

if TYPE_CHECKING:
    from rlbridge.server.session_owner import SessionOwner

log = logging.getLogger("rlbridge.server")

#: Service calls one session may have in flight.
MAX_CALLS = 16
#: Requests to one offered service that may wait for the client's answer.
MAX_PENDING = 256
@dataclass(eq=False)
class Offer:
    """A service a client provides: the middleware's server and the requests in flight."""

    request: ServiceOffer
    server: ServiceServer | None = None
    pending: dict[int, ServiceReply] = field(default_factory=dict)
    requests: int = 0
    failed: int = 0

    def stats(self) -> dict[str, Any]:
        return {"direction": "serve", "topic": self.request.service,
                "srv_type": self.request.srv_type, "requests": self.requests,
                "pending": len(self.pending), "failed": self.failed}


class SessionServices:
    """Service calls and offers of one session; see the module docstring."""

    def __init__(self, session: SessionOwner) -> None:
        self._session = session
        self._calls: dict[int, Future[dict[str, Any]]] = {}
        self.offers: dict[int, Offer] = {}
        self._ids = itertools.count(1)
        self.calls = 0
        self.call_errors = 0

    # -- calls -------------------------------------------------------------------------
    def call(self, packet: ServiceCall, via: PacketSink | None) -> None:
        s = self._session
        if len(self._calls) >= MAX_CALLS:
            self._result(ServiceResult(packet.call, int(ErrorCode.LIMIT), None,
                                       f"this session already has {MAX_CALLS} service calls "
                                       "in flight"), via)
            return
        if packet.call in self._calls:
            self._result(ServiceResult(packet.call, int(ErrorCode.UNEXPECTED), None,
                                       f"service call {packet.call} is already in flight"), via)
            return
        s.ctx.count("service_calls")
        self.calls += 1
        self._calls[packet.call] = off_loop(
            s.ctx, lambda f: self._called(packet, f, via), s.ctx.adapter.call_service,
            packet.service, packet.srv_type, packet.request, timeout_s(packet.timeout_ms))

    def _called(self, packet: ServiceCall, future: Future[dict[str, Any]],
                via: PacketSink | None) -> None:
        """Loop thread: a call completed; answer it unless the session ended meanwhile."""
        if self._calls.pop(packet.call, None) is not future or self._session.closed:
            return
        response = outcome(future, f"service call to {packet.service}")
        if isinstance(response, Failure):
            self.call_errors += 1
            self._result(ServiceResult(packet.call, int(response.code), None, response.reason),
                         via)
            return
        self._result(ServiceResult(packet.call, 0, response), via)

    def _result(self, packet: ServiceResult, via: PacketSink | None) -> None:
        self._session.send_control(packet, via)

    # -- offers ------------------------------------------------------------------------
    def offer(self, req: ServiceOffer, via: PacketSink | None, in_use: bool) -> None:
        s = self._session
        ch = req.channel
        if in_use or ch in self.offers:
            s.send_control(channel_in_use(ch), via)
            return
        offer = Offer(req)
        loop = s.ctx.loop

        def handler(request: dict[str, Any], reply: ServiceReply) -> None:
            loop.call_soon_threadsafe(self._forward, offer, request, reply)

        try:
            offer.server = s.ctx.adapter.serve_service(req.service, req.srv_type, handler)
        except BindingError as exc:
            s.send_control(TopicError(ch, int(error_code(exc.code)), exc.reason), via)
            return
        self.offers[ch] = offer
        log.info("session %d (%s): channel %d serves %s [%s]", s.id, s.name, ch, req.service,
                 req.srv_type)
        s.send_control(TopicAck(ch, req.srv_type, None), via)

    def _forward(self, offer: Offer, request: dict[str, Any], reply: ServiceReply) -> None:
        """Loop thread: pass one request on to the providing client."""
        if self.offers.get(offer.request.channel) is not offer:
            reply.fail("the provider withdrew the service")
            return
        offer.requests += 1
        if len(offer.pending) >= MAX_PENDING:
            offer.failed += 1
            reply.fail(f"the provider has {MAX_PENDING} requests unanswered")
            return
        rid = next(self._ids)
        offer.pending[rid] = reply
        self._session.send_control(ServiceRequest(offer.request.channel, rid, request))

    def reply(self, packet: ServiceReplyPacket, via: PacketSink | None) -> None:
        s = self._session
        offer = self.offers.get(packet.channel)
        if offer is None:
            s.error(ErrorCode.UNKNOWN_CHANNEL, f"channel {packet.channel} offers no service",
                    packet.channel, via)
            return
        reply = offer.pending.pop(packet.request_id, None)
        if reply is None:
            s.error(ErrorCode.UNEXPECTED, f"no request {packet.request_id} is waiting on "
                    f"channel {packet.channel}", packet.channel, via)
            return
        if packet.code != 0 or packet.response is None:
            offer.failed += 1
            reply.fail(packet.reason or "the provider reported a failure")
            return
        try:
            reply.send(packet.response)
        except BindingError as exc:
            offer.failed += 1
            reply.fail(f"the provider's response did not fit: {exc.reason}")
            s.error(ErrorCode.BAD_VALUE, f"channel {packet.channel} "
                    f"({offer.request.srv_type} response): {exc.reason}", packet.channel, via)

    def withdraw(self, channel: int) -> dict[str, Any] | None:
        """Close an offer (``TopicClose``); its stats, or None if the channel offers nothing."""
        offer = self.offers.pop(channel, None)
        if offer is None:
            return None
        self._close_offer(offer)
        return offer.stats()

    def _close_offer(self, offer: Offer) -> None:
        for reply in offer.pending.values():
            reply.fail("the provider withdrew the service")
        offer.pending.clear()
        if offer.server is not None:
            try:
                offer.server.close()
            except Exception:
                log.exception("closing the service %s", offer.request.service)

    def close(self) -> None:
        """The session ends: open calls are forgotten, offers withdrawn."""
        for future in self._calls.values():
            future.cancel()
        self._calls.clear()
        offers, self.offers = list(self.offers.values()), {}
        for offer in offers:
            self._close_offer(offer)

    def stats(self) -> dict[str, int]:
        return {"service_calls": self.calls, "service_errors": self.call_errors}

    def channel_stats(self) -> dict[str, dict[str, Any]]:
        return {str(c): o.stats() for c, o in self.offers.items()}


__all__ = ["MAX_CALLS", "MAX_PENDING", "MAX_TIMEOUT_S", "Offer", "SessionServices",
           "timeout_s"]
