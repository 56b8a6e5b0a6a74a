"""Services through a live server on the in-process bus: one client provides, others call.

Everything crosses real sockets: ``Bridge.call`` -> ``ServiceCall`` -> the server's worker
thread -> the bus -> ``ServiceRequest`` to the providing client -> its ``ServiceReply`` ->
``ServiceResult``. Every failure arrives as its own exception class, and the sessions go on.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from link_helpers import WAIT
from test_reconnect import Serve, bridges, lost, reconnected, serve

from rlbridge import LocalProtocolError
from rlbridge.client.bridge import Bridge
from rlbridge.client.service_client import CallResult
from rlbridge.client.session.services import ServiceRequests
from rlbridge.errors import (
    BadValueError,
    BindingRefused,
    ChannelClosed,
    ConnectionClosed,
    NoServiceError,
    ServiceFailed,
    ServiceTimeout,
    TypeClashError,
    UnknownTypeError,
)
from rlbridge.server import ServerThread
from waiting import wait_until

__all__ = ["bridges", "serve"]  # the reconnect tests' fixtures, used here too

SET_BOOL = "std_srvs/srv/SetBool"
TRIGGER = "std_srvs/srv/Trigger"


@pytest.fixture
def pair(server: ServerThread) -> Iterator[tuple[Bridge, Bridge]]:
    caller = Bridge.connect("127.0.0.1", server.port, name="caller", reconnect=False)
    provider = Bridge.connect("127.0.0.1", server.port, name="provider", reconnect=False)
    try:
        yield caller, provider
    finally:
        caller.close()
        provider.close()


def answer(requests: ServiceRequests, respond: Any, count: int) -> threading.Thread:
    """A provider thread: read ``count`` requests, ``respond(req)`` to each."""

    def run() -> None:
        for _ in range(count):
            try:
                respond(requests.read(timeout=20))
            except (ChannelClosed, TimeoutError):
                return

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_call_a_service_another_client_provides(pair: tuple[Bridge, Bridge]) -> None:
    caller, provider = pair
    requests = provider.serve_service("/arm/enable", SET_BOOL)
    seen: list[dict[str, Any]] = []

    def respond(req: Any) -> None:
        seen.append(req.data)
        req.reply({"success": req.data["data"], "message": "ok"})

    thread = answer(requests, respond, 3)
    for flag in (True, False, True):
        assert caller.call("/arm/enable", SET_BOOL, {"data": flag}) == {
            "success": flag, "message": "ok"}
    thread.join(10)
    assert seen == [{"data": True}, {"data": False}, {"data": True}]
    assert ("/arm/enable", SET_BOOL) in caller.service_list()
    stats = caller.server_stats()["session"]
    assert stats["service_calls"] == 3
    assert stats["service_errors"] == 0


def test_every_failure_is_its_own_exception(pair: tuple[Bridge, Bridge]) -> None:
    caller, provider = pair
    requests = provider.serve_service("/mode", SET_BOOL)
    with pytest.raises(NoServiceError, match="/nobody"):
        caller.call("/nobody", SET_BOOL, {"data": True}, timeout=0.5)
    with pytest.raises(UnknownTypeError, match="std_srvs/srv/Nope"):
        caller.call("/mode", "std_srvs/srv/Nope", {})
    with pytest.raises(BadValueError, match="bool"):
        caller.call("/mode", SET_BOOL, {"data": "on"})
    with pytest.raises(TypeClashError):
        caller.call("/mode", TRIGGER, {})
    with pytest.raises(ServiceTimeout):  # nobody reads the requests
        caller.call("/mode", SET_BOOL, {"data": True}, timeout=0.3)
    requests.read(timeout=5)  # the request that timed out is still delivered
    thread = answer(requests, lambda req: req.fail("motor driver offline"), 1)
    with pytest.raises(ServiceFailed, match="motor driver offline"):
        caller.call("/mode", SET_BOOL, {"data": True})
    thread.join(10)
    thread = answer(requests, lambda req: req.reply({"success": "maybe"}), 1)
    with pytest.raises(ServiceFailed, match="did not fit"):
        caller.call("/mode", SET_BOOL, {"data": True})
    thread.join(10)
    stats = caller.server_stats()["session"]
    assert stats["service_errors"] == 7
    # The sessions are fine: a good call still works.
    thread = answer(requests, lambda req: req.reply({"success": True}), 1)
    assert caller.call("/mode", SET_BOOL, {"data": True})["success"] is True
    thread.join(10)


def test_a_request_is_answered_once(pair: tuple[Bridge, Bridge]) -> None:
    caller, provider = pair
    requests = provider.serve_service("/once", TRIGGER)
    replies: list[Exception] = []

    def respond(req: Any) -> None:
        req.reply({"success": True})
        try:
            req.reply({"success": False})
        except LocalProtocolError as exc:
            replies.append(exc)

    thread = answer(requests, respond, 1)
    assert caller.call("/once", TRIGGER)["success"] is True
    thread.join(10)
    assert len(replies) == 1


def test_one_provider_per_service_and_withdrawing(pair: tuple[Bridge, Bridge]) -> None:
    caller, provider = pair
    requests = provider.serve_service("/single", TRIGGER)
    with pytest.raises(BindingRefused, match="already has a server"):
        caller.serve_service("/single", TRIGGER)
    requests.close()
    with pytest.raises(ChannelClosed):
        requests.read(timeout=0.1)
    # The withdrawal travels on the provider's connection: until the server has it, a call
    # on another connection may still reach the offer.
    wait_until(lambda: not caller.service_list(), "the withdrawal to reach the server",
               timeout=WAIT)
    with pytest.raises(NoServiceError):
        caller.call("/single", TRIGGER, timeout=0.5)
    again = caller.serve_service("/single", TRIGGER)  # free again
    assert again.channel_id > 0
    assert caller.server_stats()["session"]["channels"][str(again.channel_id)][
        "direction"] == "serve"


def test_service_client_does_not_block_its_loop(pair: tuple[Bridge, Bridge]) -> None:
    caller, provider = pair
    requests = provider.serve_service("/count", SET_BOOL)
    thread = answer(requests, lambda req: req.reply({"success": req.data["data"],
                                                     "message": "n"}), 3)
    client = caller.service_client("/count", SET_BOOL)
    for flag in (True, False, True):
        client.request({"data": flag})
    results = [client.responses.read(timeout=10) for _ in range(3)]
    assert [r.response["success"] for r in results if r.response] == [True, False, True]
    assert all(r.error is None for r in results)
    client.request({"data": "bad"})
    bad = client.responses.read(timeout=10)
    assert isinstance(bad, CallResult)
    assert isinstance(bad.error, BadValueError)
    client.close()
    thread.join(10)


def test_closing_the_bridge_ends_calls_and_offers(server: ServerThread) -> None:
    provider = Bridge.connect("127.0.0.1", server.port, name="p", reconnect=False)
    requests = provider.serve_service("/bye", TRIGGER)
    client = provider.service_client("/bye", TRIGGER)
    provider.close()
    with pytest.raises(ChannelClosed):
        requests.read(timeout=1)
    with pytest.raises(ChannelClosed):
        client.request({})
    with pytest.raises(ConnectionClosed):
        provider.call("/bye", TRIGGER)


def test_a_provided_service_is_offered_again_after_a_reconnect(
        serve: Serve, bridges: Callable[..., Bridge]) -> None:
    caller, provider = bridges(), bridges()
    requests = provider.serve_service("/re/offer", SET_BOOL)
    thread = answer(requests, lambda req: req.reply({"success": req.data["data"]}), 2)
    assert caller.call("/re/offer", SET_BOOL, {"data": True})["success"] is True
    serve.kill()
    wait_until(lost(caller, provider), "the link lost", timeout=WAIT)
    with pytest.raises(ConnectionClosed):  # no session to call through (within its timeout)
        caller.call("/re/offer", SET_BOOL, {"data": True}, timeout=0.1)
    serve.start()
    wait_until(reconnected(caller, provider), "the reconnect", timeout=WAIT)
    assert caller.call("/re/offer", SET_BOOL, {"data": False})["success"] is False
    thread.join(10)
