"""The adapter contract for services and latched topics (mixed into each adapter's contract).

Written against the :class:`~rlbridge.adapters.base.MiddlewareAdapter` Protocol only: a
provider's handler answers from another thread, later, as the server's does (its answer
comes over the network); calls block their caller. ``provider_failure`` is the code a caller
sees when the provider fails: ``SERVICE_FAILED`` where the middleware has an error reply,
``TIMEOUT`` on ROS 2, which has none.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import pytest
from contract import Collector

from rlbridge.adapters.base import BindingError, MiddlewareAdapter, QoS, ServiceReply
from waiting import wait_until

SET_BOOL = "std_srvs/srv/SetBool"
TRIGGER = "std_srvs/srv/Trigger"
FLOAT64 = "std_msgs/msg/Float64"


def later(action: Callable[[], None], delay: float = 0.01) -> None:
    threading.Timer(delay, action).start()


def echo_handler(request: dict[str, Any], reply: ServiceReply) -> None:
    """Answer SetBool from another thread, after the handler returned."""
    later(lambda: reply.send({"success": request["data"], "message": f"got {request['data']}"}))


class ServiceContract:
    """Services and durability; the class using it also derives from ``AdapterContract``."""

    timeout: float
    provider_failure = "SERVICE_FAILED"

    def call_code(self, adapter: MiddlewareAdapter, *args: Any, timeout: float = 0.5) -> str:
        with pytest.raises(BindingError) as info:
            adapter.call_service(*args, timeout)
        assert info.value.reason
        return info.value.code

    def test_call_a_provided_service(self, adapter: MiddlewareAdapter,
                                     topic: Callable[[str], str]) -> None:
        name = topic("srv")
        server = adapter.serve_service(name, SET_BOOL, echo_handler)
        try:
            for flag in (True, False, True):
                got = adapter.call_service(name, SET_BOOL, {"data": flag}, self.timeout)
                assert got == {"success": flag, "message": f"got {flag}"}
            assert (name, SET_BOOL) in adapter.services()
        finally:
            server.close()

    def test_defaults_fill_a_partial_request(self, adapter: MiddlewareAdapter,
                                             topic: Callable[[str], str]) -> None:
        name = topic("partial")
        server = adapter.serve_service(name, SET_BOOL, echo_handler)
        try:
            assert adapter.call_service(name, SET_BOOL, {}, self.timeout)["success"] is False
        finally:
            server.close()

    def test_unknown_service_type(self, adapter: MiddlewareAdapter,
                                  topic: Callable[[str], str]) -> None:
        assert self.call_code(adapter, topic("x"), "std_srvs/srv/NoSuch", {}) == "UNKNOWN_TYPE"
        assert self.call_code(adapter, topic("x"), "not a type", {}) == "UNKNOWN_TYPE"
        with pytest.raises(BindingError) as info:
            adapter.serve_service(topic("x"), "std_srvs/srv/NoSuch", echo_handler)
        assert info.value.code == "UNKNOWN_TYPE"

    def test_request_that_does_not_fit(self, adapter: MiddlewareAdapter,
                                       topic: Callable[[str], str]) -> None:
        for bad in ({"data": "yes"}, {"data": True, "extra": 1}):
            assert self.call_code(adapter, topic("x"), SET_BOOL, bad) == "BAD_VALUE"

    def test_bad_service_name(self, adapter: MiddlewareAdapter) -> None:
        assert self.call_code(adapter, "/a//b", SET_BOOL, {}) == "BAD_TOPIC"

    def test_no_server(self, adapter: MiddlewareAdapter, topic: Callable[[str], str]) -> None:
        assert self.call_code(adapter, topic("nobody"), SET_BOOL, {"data": True}) == "NO_SERVICE"

    def test_provider_that_never_answers(self, adapter: MiddlewareAdapter,
                                         topic: Callable[[str], str]) -> None:
        name = topic("mute")
        server = adapter.serve_service(name, TRIGGER, lambda request, reply: None)
        try:
            self.wait_served(adapter, name)
            assert self.call_code(adapter, name, TRIGGER, {}, timeout=0.3) == "TIMEOUT"
        finally:
            server.close()

    def test_provider_that_fails(self, adapter: MiddlewareAdapter,
                                 topic: Callable[[str], str]) -> None:
        name = topic("failing")
        server = adapter.serve_service(name, TRIGGER,
                                       lambda request, reply: later(lambda: reply.fail("broken")))
        try:
            self.wait_served(adapter, name)
            assert self.call_code(adapter, name, TRIGGER, {}, timeout=1.0) == self.provider_failure
        finally:
            server.close()

    def test_response_that_does_not_fit(self, adapter: MiddlewareAdapter,
                                        topic: Callable[[str], str]) -> None:
        name = topic("badresp")
        raised: list[BindingError] = []

        def handler(request: dict[str, Any], reply: ServiceReply) -> None:
            try:
                reply.send({"success": "very"})
            except BindingError as exc:
                raised.append(exc)
                reply.send({"success": True, "message": "second try"})

        server = adapter.serve_service(name, TRIGGER, handler)
        try:
            got = adapter.call_service(name, TRIGGER, {}, self.timeout)
            assert got == {"success": True, "message": "second try"}
            assert [e.code for e in raised] == ["BAD_VALUE"]
        finally:
            server.close()

    def test_one_provider_per_service(self, adapter: MiddlewareAdapter,
                                      topic: Callable[[str], str]) -> None:
        name = topic("twice")
        server = adapter.serve_service(name, SET_BOOL, echo_handler)
        try:
            with pytest.raises(BindingError) as info:
                adapter.serve_service(name, SET_BOOL, echo_handler)
            assert info.value.code == "CHANNEL_IN_USE"
        finally:
            server.close()

    def wait_served(self, adapter: MiddlewareAdapter, name: str) -> None:
        """Until the middleware lists ``name`` (discovery), bounded."""
        wait_until(lambda: any(n == name for n, _ in adapter.services()), f"{name} listed",
                   timeout=self.timeout, interval=0.02)

    # -- durability

    def test_latched_topic_reaches_a_late_subscriber(self, adapter: MiddlewareAdapter,
                                                     topic: Callable[[str], str]) -> None:
        name = topic("latched")
        pub = adapter.create_publisher(name, FLOAT64, "data",
                                       QoS(depth=2, durability="transient_local"))
        pub.publish([1.0, 2.0, 3.0])
        late = Collector()
        matched = Collector()
        subs = [adapter.subscribe(name, FLOAT64, "data", QoS(durability="transient_local"),
                                  late),
                adapter.subscribe(name, FLOAT64, "data", QoS(durability="match"), matched)]
        try:
            assert late.wait_for_count(2, self.timeout), late.values
            assert late.values[:2] == [2.0, 3.0]
            assert matched.wait_for_count(2, self.timeout), matched.values
            assert matched.values[:2] == [2.0, 3.0]
        finally:
            for sub in subs:
                sub.close()
            pub.close()

    def test_match_is_for_subscriptions(self, adapter: MiddlewareAdapter,
                                        topic: Callable[[str], str]) -> None:
        with pytest.raises(BindingError) as info:
            adapter.create_publisher(topic("m"), FLOAT64, "data", QoS(durability="match"))
        assert info.value.code == "BAD_VALUE"
