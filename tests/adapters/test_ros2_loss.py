"""ROS-side loss counted through the real ROS 2 adapter, all the way to the client.

One server with the ROS 2 adapter (in this process, on the ``ros_env`` domain), a second
adapter as "another node" publishing a burst onto a topic an SDK channel subscribes to with
the default depth (10). Every message after the first the server took is delivered to the
client or counted in ``ros_lost``: in the server's stats, its metrics, ``rlbridge stats``'s
table and the client's ``health()`` (the ``RosLoss`` report).
"""

from __future__ import annotations

import contextlib
import urllib.request
from collections.abc import Callable

import pytest

from rlbridge.adapters.base import QoS
from rlbridge.client.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.server.report import format_stats
from waiting import wait_until

ros2 = pytest.importorskip("rlbridge.adapters.ros2", exc_type=ImportError)

pytestmark = [pytest.mark.ros2, pytest.mark.timeout(120)]

N = 5000


def test_a_burst_is_delivered_or_counted(ros_env: int,
                                         unique_topic: Callable[[str], str]) -> None:
    topic = unique_topic("burst")
    with ros2.Ros2Adapter("h16a_loss_server", domain_id=ros_env) as server_side, \
            ros2.Ros2Adapter("h16a_loss_node", domain_id=ros_env) as node, \
            ServerThread(adapter=server_side, metrics_port=0, heartbeat_ms=50,
                         timeout_ms=5000) as srv, \
            Bridge.connect("127.0.0.1", srv.port, name="loss", reconnect=False) as bridge:
        ch = bridge.subscribe(topic, "std_msgs/msg/Int64", transport="tcp", blocking=True,
                              buffer_size=4 * N)
        pub = node.create_publisher(topic, "std_msgs/msg/Int64", "data", QoS(depth=N))
        probed: list[int] = []

        def probe_arrived() -> int | None:  # discovery: a probe (-k) through proves the path
            probed.append(-len(probed) - 1)
            pub.publish(probed[-1:])
            with contextlib.suppress(TimeoutError):
                return int(ch.read(timeout=0.1))
            return None

        first: int = wait_until(probe_arrived, "a probe through the server's subscription",
                                timeout=30, interval=0)
        probes = len(probed)
        assert first < 0
        pub.publish(list(range(N)))
        # Until the burst's last value: a KEEP_LAST queue never drops its newest message, so
        # it arrives, and then every earlier one is delivered or counted. Not "until 2 s of
        # quiet": a reliable writer repairs a sample lost in transport at its next heartbeat
        # (3 s with Fast DDS's defaults), so a burst can pause that long and still come.
        received: list[int] = []

        def last_came() -> bool:
            with contextlib.suppress(TimeoutError):
                received.append(ch.read(timeout=1.0))
            return received[-1:] == [N - 1]

        wait_until(last_came, lambda: f"{N - 1} ({len(received)} values came)", timeout=60,
                   interval=0)
        channel = bridge.server_stats()["session"]["channels"][str(ch.channel_id)]
        lost = channel["ros_lost"]
        print(f"{N} published in one go, {len(received)} delivered, {lost} counted lost")
        # After the first message the server took: each probe (-k) and burst value delivered,
        # or counted.
        assert len(received) + lost == (probes + first) + N
        assert [v for v in received if v >= 0] == sorted(v for v in received if v >= 0)
        if lost:
            wait_until(lambda: ch.health().ros_lost == lost, "the loss count at the client",
                       interval=0.02)
            assert ch.health().ros_lost == lost
            assert "ros_lost" in format_stats(bridge.server_stats())
            port = srv.server.address.metrics_port
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as r:
                text = r.read().decode()
            assert any(line.startswith("rlbridge_channel_values_ros_lost_total{")
                       and line.endswith(f" {lost}") for line in text.splitlines()), text
