"""``rlbridge service``/``param``/``action`` as processes against the in-process bus.

The ROS 2 side of these verbs is tested with real rclpy nodes in
tests/adapters/test_ros2_reach_e2e.py; here the commands run anywhere: a service provided by
an SDK client in this process is called by the CLI, and every failure is one stderr line.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from typing import Any

from test_cli_e2e import assert_one_line_error

from rlbridge.client.bridge import Bridge

SET_BOOL = "std_srvs/srv/SetBool"


def test_service_call_and_list(cli: Any, cli_server: Callable[..., tuple[int, Any]]) -> None:
    port, _ = cli_server()
    with Bridge.connect("127.0.0.1", port, name="provider", reconnect=False) as provider:
        requests = provider.serve_service("/arm/enable", SET_BOOL)

        def respond() -> None:
            for _ in range(2):
                req = requests.read(timeout=60)
                req.reply({"success": req.data["data"], "message": "from the SDK"})

        thread = threading.Thread(target=respond, daemon=True)
        thread.start()
        for text, flag in (("{data: true}", True), ('{"data": false}', False)):
            done = cli.run("service", "call", "/arm/enable", SET_BOOL, text, "--port", str(port))
            assert done.returncode == 0, done.stderr
            assert json.loads(done.stdout) == {"success": flag, "message": "from the SDK"}
        thread.join(10)
        done = cli.run("service", "list", "--show-types", "--port", str(port))
        assert done.stdout.splitlines() == [f"/arm/enable [{SET_BOOL}]"]


def test_failures_are_one_line(cli: Any, cli_server: Callable[..., tuple[int, Any]]) -> None:
    port, _ = cli_server()
    p = ("--port", str(port))
    assert_one_line_error(cli.run("service", "call", "/none", SET_BOOL, "{data: true}",
                                  "--timeout", "0.2", *p), "no server for service '/none'")
    assert_one_line_error(cli.run("service", "call", "/none", "std_srvs/srv/Nope", *p),
                          "unknown service type")
    assert_one_line_error(cli.run("service", "call", "/none", SET_BOOL, "{data: [", *p),
                          "neither JSON nor YAML")
    assert_one_line_error(cli.run("param", "get", "some_node", "gain", "--timeout", "0.2",
                                  *p), "no ROS nodes and no parameters")
    assert_one_line_error(cli.run("action", "send", "/fib", "test_msgs/action/Fibonacci",
                                  "{order: 3}", *p), "no action")
