"""End to end with real rclpy nodes: services both ways, an action, parameters, a latched topic.

In a private network namespace (:mod:`reach_netns`): ``rlbridge serve --adapter ros2``, a
plain rclpy node (``ros2_reach_peer.py serve``: services, a Fibonacci action server,
parameters, a latched topic), and the SDK in this process. One server, peer and session serve
the module.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from collections.abc import Iterator
from typing import Any

import pytest
from reach_netns import PEER, LoggedProcess, World, in_namespace, run_cli, world

from waiting import wait_until

pytest.importorskip("test_msgs.action", reason="needs ros-test-msgs")
pytest.importorskip("std_srvs.srv", reason="needs ros-std-srvs")

from rlbridge import ParameterError, QoS
from rlbridge.client.bridge import Bridge
from rlbridge.errors import (
    BadValueError,
    NoServiceError,
    UnknownTypeError,
)

pytestmark = [pytest.mark.ros2, pytest.mark.netem, pytest.mark.timeout(180)]

SET_BOOL = "std_srvs/srv/SetBool"
BASIC = "test_msgs/srv/BasicTypes"
FIBONACCI = "test_msgs/action/Fibonacci"


@pytest.fixture(scope="module")
def reach(tmp_path_factory: pytest.TempPathFactory) -> Iterator[World]:
    with world("reach", tmp_path_factory.mktemp("ros_log"), serve_peer=True) as made:
        yield made


@pytest.fixture(scope="module")
def sdk(reach: World) -> Iterator[Bridge]:
    bridge = reach.connect("reach-sdk")
    try:
        yield bridge
    finally:
        bridge.close()


def test_call_set_bool_from_the_sdk(sdk: Bridge) -> None:
    assert sdk.call("/reach/set_bool", SET_BOOL, {"data": True}, timeout=20) == {
        "success": True, "message": "set to True"}
    assert sdk.call("/reach/set_bool", SET_BOOL, {"data": False}) == {
        "success": False, "message": "set to False"}
    assert ("/reach/set_bool", SET_BOOL) in sdk.service_list()


def test_call_basic_types_from_the_sdk(sdk: Bridge) -> None:
    request: dict[str, Any] = {
        "bool_value": True, "byte_value": 7, "char_value": 65, "float32_value": 0.5,
        "float64_value": -1e300, "int8_value": -128, "uint8_value": 255,
        "int16_value": -32768, "uint16_value": 65535, "int32_value": -(2**31),
        "uint32_value": 2**32 - 1, "int64_value": -(2**63), "uint64_value": 2**64 - 1,
        "string_value": "héllo"}
    response = sdk.call("/reach/basic", BASIC, request, timeout=20)
    assert response == {**request, "string_value": "olléh"}


def test_service_errors(sdk: Bridge) -> None:
    with pytest.raises(NoServiceError):
        sdk.call("/reach/nobody", SET_BOOL, {"data": True}, timeout=0.5)
    with pytest.raises(UnknownTypeError, match="std_srvs has"):
        sdk.call("/reach/set_bool", "std_srvs/srv/Nope", {})
    with pytest.raises(BadValueError, match="int8_value"):
        sdk.call("/reach/basic", BASIC, {"int8_value": 300})


def test_a_service_the_sdk_provides_called_by_rclpy(reach: World, sdk: Bridge) -> None:
    requests = sdk.serve_service("/reach/sdk_arm", SET_BOOL)
    seen: list[dict[str, Any]] = []

    def provide() -> None:
        req = requests.read(timeout=60)
        seen.append(req.data)
        req.reply({"success": True, "message": "armed by the SDK"})

    thread = threading.Thread(target=provide, daemon=True)
    thread.start()
    caller = LoggedProcess(in_namespace(reach.namespace, [
        sys.executable, str(PEER), "call", "/reach/sdk_arm"]), reach.env)
    assert caller.wait(90) == 0, caller.log
    caller.stop()
    thread.join(10)
    assert seen == [{"data": True}]
    answer = [line for line in caller.lines if line.startswith("{")]
    assert [json.loads(line) for line in answer] == [
        {"success": True, "message": "armed by the SDK"}], caller.log
    requests.close()


def test_fibonacci_action_with_feedback(sdk: Bridge) -> None:
    goal = sdk.send_goal("/reach/fibonacci", FIBONACCI, {"order": 6}, timeout=20)
    result = goal.result(timeout=60)
    assert result == {"sequence": [0, 1, 1, 2, 3, 5, 8]}
    assert goal.status == "succeeded"
    feedback = goal.feedback.read_many()
    assert [f["sequence"] for f in feedback] == [
        [0, 1, 1], [0, 1, 1, 2], [0, 1, 1, 2, 3], [0, 1, 1, 2, 3, 5], [0, 1, 1, 2, 3, 5, 8]]


def test_fibonacci_action_cancelled(sdk: Bridge) -> None:
    goal = sdk.send_goal("/reach/fibonacci", FIBONACCI, {"order": 10_000}, timeout=20)
    first = goal.feedback.read(timeout=30)
    assert first["sequence"][:3] == [0, 1, 1]
    goal.cancel()
    result = goal.result(timeout=60)
    assert goal.status == "canceled"
    assert len(result["sequence"]) < 10_000


def test_action_errors(sdk: Bridge) -> None:
    with pytest.raises(NoServiceError, match="no action server"):
        sdk.send_goal("/reach/nobody", FIBONACCI, {"order": 1}, timeout=0.5)
    with pytest.raises(BadValueError):
        sdk.send_goal("/reach/fibonacci", FIBONACCI, {"order": "many"})


def test_parameters_read_listed_and_set(sdk: Bridge) -> None:
    assert sdk.get_parameter("reach_peer", "gain", timeout=20) == 1.5
    assert sdk.get_parameter("/reach_peer", "mode") == "auto"
    assert sdk.get_parameter("reach_peer", "enabled") is True
    assert {"gain", "mode", "enabled"} <= set(sdk.list_parameters("reach_peer"))
    sdk.set_parameter("reach_peer", "gain", 2.5)
    assert sdk.get_parameter("reach_peer", "gain") == 2.5
    with pytest.raises(ParameterError, match="refused"):
        sdk.set_parameter("reach_peer", "gain", "high")  # a double stays a double
    with pytest.raises(ParameterError, match="no parameter 'nope'"):
        sdk.get_parameter("reach_peer", "nope")


@pytest.mark.parametrize("transport", ["tcp", "udp"])
@pytest.mark.parametrize("field", ["data", None])
@pytest.mark.parametrize("durability", ["transient_local", "match"])
def test_latched_topic_published_before_the_client_connected(
        sdk: Bridge, durability: Any, field: str | None, transport: Any) -> None:
    """The value a latched topic holds when the channel binds arrives on either transport
    (over UDP the server's subscription is reliable, or DDS would send it no history)."""
    ch = sdk.subscribe("/reach/map", "std_msgs/msg/String", field, transport=transport,
                       blocking=True, qos=QoS(durability=durability))
    assert ch.read(timeout=30) == ("map v1" if field else {"data": "map v1"})
    sdk.unsubscribe(ch)


def _published(sdk: Bridge, topic: str) -> bool:
    """The server published a value of this session's channel on ``topic``."""
    channels = sdk.server_stats()["session"]["channels"]
    return any(c["topic"] == topic and c["values_in"] > 0 for c in channels.values())


@pytest.mark.parametrize("transport", ["tcp", "udp"])
def test_a_latched_value_from_the_sdk_reaches_a_late_rclpy_subscriber(
        reach: World, sdk: Bridge, transport: Any) -> None:
    topic = f"/reach/sdk_map_{transport}"
    out = sdk.publish(topic, "std_msgs/msg/String", transport=transport,
                      qos=QoS(durability="transient_local"))
    # Written until the server published it (again and again: a datagram may be lost).
    wait_until(lambda: _published(sdk, topic), f"the server to publish on {topic}", timeout=30,
               interval=0.2, between=lambda: out.write(f"sdk map over {transport}"))
    late = reach.peer("latched", topic)
    assert late.wait(90) == 0, late.log
    late.stop()
    assert f"got sdk map over {transport}" in late.lines[-1], late.log
    sdk.unsubscribe(out)


# -- the CLI, as processes in the namespace ----------------------------------------------------


def cli(w: World, *args: str) -> subprocess.CompletedProcess[str]:
    return run_cli(w.namespace, w.env, *args, "--port", str(w.port))


def test_cli_service_call_and_list(reach: World) -> None:
    done = cli(reach, "service", "call", "/reach/set_bool", SET_BOOL, "{data: true}",
               "--timeout", "20")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == {"success": True, "message": "set to True"}
    done = cli(reach, "service", "call", "/reach/basic", BASIC,
               '{"int32_value": -7, "string_value": "abc", "float64_value": 2.5}')
    assert done.returncode == 0, done.stderr
    response = json.loads(done.stdout)
    assert (response["int32_value"], response["string_value"], response["float64_value"]) == (
        -7, "cba", 2.5)
    done = cli(reach, "service", "list", "--show-types")
    assert done.returncode == 0, done.stderr
    assert f"/reach/set_bool [{SET_BOOL}]" in done.stdout.splitlines()


def test_cli_service_errors_are_one_line(reach: World) -> None:
    for args, phrase in [
        (("/reach/nobody", SET_BOOL, "{data: true}", "--timeout", "0.5"), "no server"),
        (("/reach/set_bool", SET_BOOL, "{data: [}"), "neither JSON nor YAML"),
        (("/reach/set_bool", SET_BOOL, "[1, 2]"), "mapping of fields"),
        (("/reach/set_bool", SET_BOOL, "{data: 5}"), "bool"),
    ]:
        done = cli(reach, "service", "call", *args)
        assert done.returncode != 0
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1, done.stderr
        assert phrase in lines[0]


def test_cli_param_get_set_list(reach: World) -> None:
    done = cli(reach, "param", "list", "reach_peer", "--timeout", "20")
    assert done.returncode == 0, done.stderr
    assert {"gain", "mode", "enabled"} <= set(done.stdout.split())
    done = cli(reach, "param", "set", "reach_peer", "mode", "manual")
    assert done.returncode == 0, done.stderr
    done = cli(reach, "param", "get", "reach_peer", "mode")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == "manual"
    done = cli(reach, "param", "set", "reach_peer", "enabled", "3")
    assert done.returncode == 1
    assert "refused" in done.stderr


def test_cli_action_send_shows_feedback(reach: World) -> None:
    done = cli(reach, "action", "send", "/reach/fibonacci", FIBONACCI, "{order: 4}",
               "--timeout", "30")
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    assert [line["feedback"]["sequence"] for line in lines[:-1]] == [
        [0, 1, 1], [0, 1, 1, 2], [0, 1, 1, 2, 3]]
    assert lines[-1] == {"result": {"sequence": [0, 1, 1, 2, 3]}, "status": "succeeded"}
