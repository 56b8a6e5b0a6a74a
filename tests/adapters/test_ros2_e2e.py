"""End to end: rclpy nodes in other processes <-> ``rlbridge serve --adapter ros2`` <-> the SDK.

Three kinds of process, as deployed: the bridge server started through the command line (port
0, its port read from its own log line), a plain rclpy node (``ros2_peer.py``, which imports
nothing from rlbridge), and this test process as the SDK client (``Bridge.connect``). Values
cross both ways over TCP and UDP channels, for scalar fields, nested fields and whole messages;
binding errors travel back as topic-errors that the SDK raises as its own exception classes,
and the session keeps working after each of them.

One server, one peer and one SDK session serve the whole module (every test uses its own
topics), so the module costs one server start-up, not one per test.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import pytest
from ros_peers import env_for

from localhost import rlbridge_command
from rlbridge import QoS
from rlbridge.client.bridge import Bridge
from rlbridge.errors import NoSuchFieldError, TypeClashError, UnknownTypeError
from waiting import poll_until, wait_until

if TYPE_CHECKING:
    from ros_peers import PeerProcess

pytestmark = [pytest.mark.ros2, pytest.mark.timeout(90)]

#: Bound of every wait (discovery and start-up on a loaded 2-core machine take seconds).
TIMEOUT = 20.0
SERVING = re.compile(r"rlbridge listening on [^ ]+ port (\d+) ")

ZERO3 = {"x": 0.0, "y": 0.0, "z": 0.0}
TWIST = {"linear": {"x": 0.5, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": -0.25}}
POSE = {"position": {"x": 1.0, "y": 2.0, "z": 3.0},
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


class CliServer:
    """``rlbridge serve --adapter ros2 --port 0`` in a subprocess; its stderr kept in a list.

    ``python`` picks the interpreter (and so the rclpy) the server runs on.
    """

    def __init__(self, node_name: str, python: str = sys.executable) -> None:
        command = rlbridge_command(python)
        env = {**env_for(python), "PYTHONUNBUFFERED": "1"}
        env.pop("PYTHONWARNINGS", None)
        self.proc = subprocess.Popen(
            [*command, "--log-level", "info", "serve", "--port", "0", "--adapter", "ros2",
             "--node-name", node_name, "--timeout-ms", "5000"],  # the watchdog: not tested
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            text=True, env=env,
        )
        self.lines: list[str] = []
        self._port: int | None = None
        self._ready = threading.Event()
        self._reader = threading.Thread(target=self._read, name="e2e-server-log", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:  # drained to the end, so the server never blocks on it
            self.lines.append(line)
            match = SERVING.search(line)
            if match and self._port is None:
                self._port = int(match.group(1))
                self._ready.set()
        self._ready.set()

    def port(self) -> int:
        if not self._ready.wait(TIMEOUT * 2) or self._port is None:
            raise AssertionError(f"rlbridge serve did not start: {''.join(self.lines)}")
        return self._port

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(TIMEOUT)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        self._reader.join(5.0)
        if self.proc.stderr is not None:
            self.proc.stderr.close()
        return self.proc.returncode


@pytest.fixture(scope="module")
def ros2_server(ros_env: int) -> Iterator[CliServer]:
    """The bridge server with the ROS 2 adapter, in the ``ros_env``-scoped environment."""
    srv = CliServer(f"rlbridge_e2e_{os.getpid()}")
    try:
        srv.port()
        yield srv
    finally:
        code = srv.stop()
    log = "".join(srv.lines)
    assert "Traceback" not in log, log
    assert code == 0, log


@pytest.fixture(scope="module")
def sdk(ros2_server: CliServer) -> Iterator[Bridge]:
    """One SDK session shared by the module: errors must not end it."""
    port = ros2_server.port()
    with Bridge.connect("127.0.0.1", port, name="e2e-ros2", timeout=TIMEOUT) as bridge:
        yield bridge


def _tail_is(expected: list[Any]) -> Callable[[list[Any]], bool]:
    return lambda values: values[len(values) - len(expected):] == expected


def _read_until(ch: Any, done: Callable[[list[Any]], bool], got: list[Any]) -> bool:
    """Blocking reads into ``got`` until ``done(got)``; whether it came within ``TIMEOUT``
    (callers assert, showing ``got``)."""
    def read_one() -> bool:
        if not done(got):
            with contextlib.suppress(TimeoutError):
                got.append(ch.read(0.2))
        return done(got)

    return bool(poll_until(read_one, timeout=TIMEOUT, interval=0))


#: (transport, type, field, probe, values): rclpy publisher -> bridge -> SDK subscriber.
INTO_SDK = [
    ("tcp", "std_msgs/msg/Float64", "data", -1.0, [0.5, 1e300, -2.25]),
    ("udp", "std_msgs/msg/Float64", "data", -1.0, [0.5, -2.25]),
    ("tcp", "std_msgs/msg/String", "data", "probe", ["", "hello ROS ✓"]),
    ("udp", "std_msgs/msg/Int32", "data", 0, [-(2**31), 7, 2**31 - 1]),
    ("udp", "std_msgs/msg/Bool", "data", False, [True, False, True]),
    ("tcp", "geometry_msgs/msg/Twist", "linear.x", 0.0, [0.25, -1.5]),
    ("udp", "geometry_msgs/msg/Pose", "position.z", 0.0, [3.0, -0.5]),
    ("tcp", "geometry_msgs/msg/Twist", None, {"linear": ZERO3, "angular": ZERO3}, [TWIST]),
    ("udp", "geometry_msgs/msg/Pose", None, {}, [POSE]),
]

#: (transport, type, field, probe, values, what the rclpy subscriber sees).
FROM_SDK = [
    ("tcp", "std_msgs/msg/Float64", "data", -1.0, [0.5, -2.25], None),
    ("udp", "std_msgs/msg/Float64", "data", -1.0, [0.5, -2.25], None),
    ("tcp", "std_msgs/msg/Int32", "data", 0, [-5, 2**31 - 1], None),
    ("udp", "std_msgs/msg/Bool", "data", False, [True, True], None),
    ("udp", "std_msgs/msg/String", "data", "probe", ["hello ROS ✓"], None),
    ("tcp", "geometry_msgs/msg/Twist", "linear.x", 0.0, [0.25, 0.75], None),
    ("udp", "geometry_msgs/msg/Pose", "position.z", 0.0, [3.0], None),
    # A partial mapping: the rclpy node sees the whole message, the rest at its defaults.
    ("tcp", "geometry_msgs/msg/Twist", None, {}, [{"linear": {"x": 0.5}, "angular": {"z": -0.25}}],
     [TWIST]),
    ("udp", "geometry_msgs/msg/Pose", None, {}, [POSE], None),
]


def _ids(cases: list[tuple[Any, ...]]) -> list[str]:
    return [f"{c[0]}-{c[1].split('/')[-1]}-{c[2] or 'whole'}" for c in cases]


@pytest.mark.parametrize(("transport", "msg_type", "field", "probe", "values"), INTO_SDK,
                         ids=_ids(INTO_SDK))
def test_rclpy_publisher_to_sdk(
    sdk: Bridge, peer: PeerProcess, unique_topic: Callable[[str], str],
    transport: str, msg_type: str, field: str | None, probe: Any, values: list[Any],
) -> None:
    topic = unique_topic(f"in_{transport}")
    ch = sdk.subscribe(topic, msg_type, field, transport=transport,  # type: ignore[arg-type]
                       blocking=True, buffer_size=1024)
    handle = peer.call("pub", topic=topic, type=msg_type, field=field)
    got: list[Any] = []

    def probe_arrived() -> bool:  # discovery: the first probe that arrives proves the path
        peer.call("publish", handle=handle, values=[probe])
        with contextlib.suppress(TimeoutError):
            got.append(ch.read(0.1))
        return bool(got)

    wait_until(probe_arrived, "the rclpy publisher to reach the SDK", timeout=TIMEOUT,
               interval=0.0)
    peer.call("publish", handle=handle, values=values)
    assert _read_until(ch, _tail_is(values), got), got
    probe_seen = got[0]
    if isinstance(probe, dict) and not probe:
        probe = probe_seen  # an empty mapping published: every field at its default
    assert all(v == probe for v in got[: len(got) - len(values)]), got
    sdk.unsubscribe(ch)
    peer.call("close", handle=handle)


@pytest.mark.parametrize(("transport", "msg_type", "field", "probe", "values", "seen"), FROM_SDK,
                         ids=_ids(FROM_SDK))
def test_sdk_publisher_to_rclpy_subscriber(
    sdk: Bridge, peer: PeerProcess, unique_topic: Callable[[str], str],
    transport: str, msg_type: str, field: str | None, probe: Any, values: list[Any],
    seen: list[Any] | None,
) -> None:
    topic = unique_topic(f"out_{transport}")
    # The server's publisher is best effort for UDP channels and reliable for TCP ones (a
    # reliable rclpy subscription would not match a best-effort publisher, as in any ROS graph).
    reliability = "best_effort" if transport == "udp" else "reliable"
    handle = peer.call("sub", topic=topic, type=msg_type, field=field, reliability=reliability)
    out = sdk.publish(topic, msg_type, field, transport=transport)  # type: ignore[arg-type]
    wait_until(lambda: peer.wait_messages(handle, bool, 0.1),
               "the SDK's publisher to reach the rclpy node", timeout=TIMEOUT, interval=0.0,
               between=lambda: out.write(probe))
    for value in values:
        out.write(value)
    expected = values if seen is None else seen
    assert peer.wait_messages(handle, _tail_is(expected), TIMEOUT), peer.messages(handle)
    sdk.unsubscribe(out)
    peer.call("close", handle=handle)


def test_whole_message_in_and_field_out_on_one_topic(
    sdk: Bridge, peer: PeerProcess, unique_topic: Callable[[str], str]
) -> None:
    """``/cmd_vel`` as a ROS user has it: the SDK writes ``linear.x``, reads whole Twists."""
    topic = unique_topic("cmd_vel")
    twist = "geometry_msgs/msg/Twist"
    whole = sdk.subscribe(topic, twist, None, transport="tcp", blocking=True, buffer_size=64)
    out = sdk.publish(topic, twist, "linear.x", transport="tcp")
    handle = peer.call("sub", topic=topic, type=twist, field=None)
    got: list[Any] = []

    def write_and_read() -> None:
        out.write(0.0)
        with contextlib.suppress(TimeoutError):
            got.append(whole.read(0.1))

    wait_until(lambda: got and peer.messages(handle), "the binding to reach the rclpy node",
               timeout=TIMEOUT, interval=0.0, between=write_and_read)
    out.write(0.5)
    expected = {"linear": {**ZERO3, "x": 0.5}, "angular": ZERO3}
    assert _read_until(whole, _tail_is([expected]), got), got
    assert peer.wait_messages(handle, _tail_is([expected]), TIMEOUT), peer.messages(handle)
    sdk.unsubscribe(out)
    sdk.unsubscribe(whole)
    peer.call("close", handle=handle)


def _wait_graph_type(sdk: Bridge, topic: str, msg_type: str) -> None:
    wait_until(lambda: [topic, msg_type] in [list(t) for t in sdk.server_stats()["topics"]],
               f"{topic} in the server's graph", timeout=TIMEOUT, interval=0.05)


def test_binding_errors_over_the_wire_leave_the_session_working(
    sdk: Bridge, peer: PeerProcess, unique_topic: Callable[[str], str]
) -> None:
    with pytest.raises(UnknownTypeError, match=r"NoSuchType") as unknown:
        sdk.subscribe(unique_topic("u"), "std_msgs/msg/NoSuchType", "data")
    assert "Float64" in unknown.value.reason  # the reason lists what the package has

    with pytest.raises(UnknownTypeError, match=r"sensor_msgs") as missing:
        sdk.publish(unique_topic("m"), "sensor_msgs/msg/Imu", "linear_acceleration.x")
    assert missing.value.code.name == "PACKAGE_MISSING"
    assert "ros-sensor-msgs" in missing.value.reason  # what to install

    with pytest.raises(NoSuchFieldError, match=r"linear\.w|'w'") as no_field:
        sdk.subscribe(unique_topic("f"), "geometry_msgs/msg/Twist", "linear.w", transport="tcp")
    assert "z" in no_field.value.reason  # the fields that exist at that level

    # A clash with a topic an rclpy node in another process owns.
    theirs = unique_topic("theirs")
    handle = peer.call("pub", topic=theirs, type="std_msgs/msg/Float64")
    _wait_graph_type(sdk, theirs, "std_msgs/msg/Float64")
    with pytest.raises(TypeClashError) as clash:
        sdk.subscribe(theirs, "std_msgs/msg/Int32", "data")
    assert "std_msgs/msg/Float64" in clash.value.reason
    assert "std_msgs/msg/Int32" in clash.value.reason
    peer.call("close", handle=handle)

    # A clash with a topic this bridge binds itself (another channel, same session).
    ours = unique_topic("ours")
    held = sdk.publish(ours, "std_msgs/msg/Float64", "data", transport="tcp")
    with pytest.raises(TypeClashError, match=r"std_msgs/msg/Bool"):
        sdk.subscribe(ours, "std_msgs/msg/Bool", "data", transport="tcp")

    # The session is still up and the refused channels left nothing behind: a round trip works.
    assert not sdk.closed
    echo = sdk.subscribe(ours, "std_msgs/msg/Float64", "data", transport="tcp", blocking=True,
                         buffer_size=64)
    got: list[Any] = []

    def round_trip() -> None:
        held.write(42.0)
        with contextlib.suppress(TimeoutError):
            got.append(echo.read(0.1))

    wait_until(lambda: 42.0 in got, "a round trip after the errors", timeout=TIMEOUT,
               interval=0.0, between=round_trip)
    sdk.unsubscribe(echo)
    sdk.unsubscribe(held)


def test_sdk_qos_reaches_the_ros_graph(
    sdk: Bridge, peer: PeerProcess, unique_topic: Callable[[str], str],
) -> None:
    """A UDP channel defaults to a best-effort publisher, which a reliable rclpy subscription
    does not match; ``reliability="reliable"`` from the SDK makes the server's publisher
    reliable, so the same subscription now receives."""
    topic = unique_topic("qos")
    handle = peer.call("sub", topic=topic, type="std_msgs/msg/Float64", field="data",
                       reliability="reliable")
    out = sdk.publish(topic, "std_msgs/msg/Float64", transport="udp",
                      qos=QoS(reliability="reliable", depth=5))
    wait_until(lambda: peer.wait_messages(handle, bool, 0.1),
               "a reliable SDK publisher to reach rclpy", timeout=TIMEOUT, interval=0.0,
               between=lambda: out.write(1.5))
    assert peer.wait_messages(handle, lambda got: 1.5 in got, TIMEOUT), peer.messages(handle)
    sdk.unsubscribe(out)
    peer.call("close", handle=handle)
