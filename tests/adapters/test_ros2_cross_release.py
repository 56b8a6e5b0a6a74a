"""A graph across ROS 2 releases: rlbridge's server on one release's rclpy, ROS nodes on another.

Nodes of different ROS 2 releases talk to each other through DDS (RTPS is the wire protocol;
the releases share the message definitions of ``std_msgs`` and ``geometry_msgs``). A user on
Jazzy (rclpy 7.1, Fast DDS 2.14) whose bridge server runs in a venv with the current wheels
(rclpy 9.1, Fast DDS 3.2), or the reverse, must see values cross. This module proves it here.

The other release is the interpreter named by ``$RLBRIDGE_ROS_OTHER_PYTHON``: scripts/test.sh
sets it to ``.venv-jazzy/bin/python`` (Jazzy's wheels, ``pip install -e '.[ros2-jazzy]'``) while
this test process runs in ``.venv`` (the current wheels). Without it the module skips, saying
so. Both pairings run, each with its own server and node processes:

* ``server-here``: ``rlbridge serve --adapter ros2`` on this interpreter's rclpy, the plain
  rclpy node (ros2_peer.py, which imports nothing from rlbridge) on the other release;
* ``server-other``: the server on the other release's rclpy, the node on this one's.

In each, the end-to-end value tests of test_ros2_e2e.py run unchanged: scalar fields, nested
fields and whole messages, over TCP and UDP channels, from the ROS node to the SDK and back.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from typing import Any

import pytest
import test_ros2_e2e as e2e
from ros_peers import PEER_SCRIPT, PeerProcess, env_for

from rlbridge.client.bridge import Bridge

OTHER_PYTHON = os.environ.get("RLBRIDGE_ROS_OTHER_PYTHON", "")

pytestmark = [
    pytest.mark.ros2,
    pytest.mark.timeout(120),
    pytest.mark.skipif(not OTHER_PYTHON, reason="set RLBRIDGE_ROS_OTHER_PYTHON to a Python "
                       "whose rclpy is another ROS 2 release (scripts/test.sh does)"),
]


def rclpy_release(python: str) -> dict[str, Any]:
    """What ``ros2_peer.py release`` says about ``python``'s rclpy."""
    out = subprocess.run([python, str(PEER_SCRIPT), "release"], capture_output=True, text=True,
                         env=env_for(python), timeout=60, check=False)
    assert out.returncode == 0, f"{python} has no working rclpy: {out.stderr[-2000:]}"
    info: dict[str, Any] = json.loads(out.stdout.splitlines()[-1])
    return info


@pytest.fixture(scope="module")
def releases(ros_env: int) -> dict[str, dict[str, Any]]:
    """The two rclpy releases; they must differ, or this module would prove nothing."""
    found = {"here": rclpy_release(sys.executable), "other": rclpy_release(OTHER_PYTHON)}
    assert found["here"]["rclpy"] != found["other"]["rclpy"], found
    print(f"\ncross-release: here {found['here']}, other {found['other']}")
    return found


@pytest.fixture(scope="module", params=["server-here", "server-other"])
def pairing(request: pytest.FixtureRequest, releases: dict[str, dict[str, Any]]
            ) -> Iterator[tuple[Bridge, PeerProcess]]:
    """A server on one release, a ROS node on the other, and an SDK session to the server."""
    here, other = sys.executable, OTHER_PYTHON
    server_python, node_python = (here, other) if request.param == "server-here" else (other, here)
    server = e2e.CliServer(f"rlbridge_xrel_{os.getpid()}", python=server_python)
    node = PeerProcess(node_python)
    try:
        with Bridge.connect("127.0.0.1", server.port(), name=f"xrel-{request.param}",
                            timeout=e2e.TIMEOUT) as bridge:
            yield bridge, node
    finally:
        node.close()
        code = server.stop()
    log = "".join(server.lines)
    assert "Traceback" not in log, log
    assert code == 0, log


@pytest.fixture
def sdk(pairing: tuple[Bridge, PeerProcess]) -> Bridge:
    """The SDK session of the current pairing (the name the e2e tests ask for)."""
    return pairing[0]


@pytest.fixture
def peer(pairing: tuple[Bridge, PeerProcess]) -> PeerProcess:
    """The ROS node of the current pairing, on the other release than the server."""
    return pairing[1]


# The end-to-end value tests, run here with the fixtures above (same names, other releases).
test_rclpy_publisher_to_sdk = e2e.test_rclpy_publisher_to_sdk
test_sdk_publisher_to_rclpy_subscriber = e2e.test_sdk_publisher_to_rclpy_subscriber
test_whole_message_in_and_field_out_on_one_topic = (
    e2e.test_whole_message_in_and_field_out_on_one_topic)
