"""Blocking middleware work that fails (server/worker_calls.py): a service call and a goal.

Both run on the server's worker pool and come back to the loop the same way: a middleware
that raises something other than ``BindingError`` (a crashed driver, a bug) is answered
``INTERNAL`` with the exception's type and message, and the session goes on.
"""

from __future__ import annotations

from typing import Any

import pytest

from rlbridge import RlbridgeError
from rlbridge.adapters.inproc import InProcessBus
from rlbridge.csp.bridge import Bridge
from rlbridge.server import ServerConfig, ServerThread

F64 = "std_msgs/msg/Float64"


class CrashingBus(InProcessBus):
    """The in-process bus, except that calls and goals crash inside the middleware."""

    def call_service(self, service: str, srv_type: str, request: dict[str, Any],
                     timeout: float) -> dict[str, Any]:
        raise RuntimeError(f"driver of {service} crashed")

    def send_goal(self, action: str, *args: Any) -> Any:
        raise RuntimeError(f"driver of {action} crashed")


def test_a_crash_in_the_middleware_is_an_internal_error_and_the_session_goes_on() -> None:
    with ServerThread(ServerConfig(port=0), adapter=CrashingBus()) as srv, \
            Bridge.connect("127.0.0.1", srv.port, name="caller", reconnect=False) as bridge:
        with pytest.raises(RlbridgeError, match="RuntimeError: driver of /arm/enable crashed"):
            bridge.call("/arm/enable", "std_srvs/srv/SetBool", {"data": True})
        with pytest.raises(RlbridgeError, match="RuntimeError: driver of /fib crashed"):
            bridge.send_goal("/fib", "test_msgs/action/Fibonacci", {"order": 3})
        assert bridge.server_stats()["session"]["service_errors"] == 1
        out = bridge.publish("/still/here", F64, transport="tcp")  # the session is fine
        sub = bridge.subscribe("/still/here", F64, transport="tcp", blocking=True)
        out.write(1.5)
        bridge.send(wait=True)
        assert sub.read(timeout=30) == 1.5
