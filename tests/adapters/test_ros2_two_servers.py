"""Scale out on the graph: two bridge servers on two "machines", one ROS 2 graph.

Two network namespaces joined by a veth pair stand for two hosts on one LAN. Each runs
``rlbridge serve --adapter ros2``; DDS discovery between them uses the LAN (``SUBNET``) with
each host named as the other's static peer (multicast-free, as on many real networks). A value
written by an SDK client of one server reaches an SDK client of the other: the two bridges meet
only in the ROS graph, with no rlbridge link of their own (docs/ros2.md).
"""

from __future__ import annotations

import secrets
from collections.abc import Iterator
from contextlib import suppress

import pytest
from reach_netns import remove_namespace, require_netns, ros_env, start_server

from rlbridge.client.bridge import Bridge
from rlbridge.netem import netns
from waiting import wait_until

pytestmark = [pytest.mark.ros2, pytest.mark.netem, pytest.mark.timeout(180)]

ADDRESSES = ("10.216.7.1", "10.216.7.2")


@pytest.fixture
def two_hosts() -> Iterator[tuple[str, str]]:
    require_netns()
    token = secrets.token_hex(2)
    names = (f"h16a-{token}-a", f"h16a-{token}-b")
    links = (f"h16a{token}a", f"h16a{token}b")
    made: list[str] = []
    try:
        for name in names:
            netns.create_namespace(name)
            made.append(name)
        netns.run_ip("link", "add", links[0], "type", "veth", "peer", "name", links[1])
        for name, link, address in zip(names, links, ADDRESSES, strict=True):
            netns.run_ip("link", "set", link, "netns", name)
            netns.run_ip("-n", name, "addr", "add", f"{address}/24", "dev", link)
            netns.run_ip("-n", name, "link", "set", link, "up")
        yield names
    finally:
        for name in made:
            with suppress(netns.NetnsError):
                remove_namespace(name)


def test_a_value_crosses_from_one_server_to_the_other(
        two_hosts: tuple[str, str], tmp_path_factory: pytest.TempPathFactory) -> None:
    servers = []
    bridges: list[Bridge] = []
    try:
        for i, name in enumerate(two_hosts):
            env = ros_env(tmp_path_factory.mktemp(f"ros_log_{i}"), domain=65)
            env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"
            env["ROS_STATIC_PEERS"] = ADDRESSES[1 - i]
            server, port = start_server(name, env, f"h16a_bridge_{'ab'[i]}")
            servers.append(server)
            bridges.append(netns.call_in_namespace(name, lambda port=port: Bridge.connect(
                "127.0.0.1", port, name="scale-out", timeout=20.0, reconnect=False)))
        writer, reader = bridges
        inbox = reader.subscribe("/h16a/shared", "std_msgs/msg/Float64", transport="tcp",
                                 blocking=True)
        out = writer.publish("/h16a/shared", "std_msgs/msg/Float64", transport="tcp")

        def arrived() -> float | None:  # discovery across the "LAN"
            out.write(42.5)
            with suppress(TimeoutError):
                got: float = inbox.read(timeout=0.2)
                return got
            return None

        assert wait_until(arrived, "a value across the two servers", timeout=60,
                          interval=0.0) == 42.5
        topics = dict(reader.server_stats()["topics"])
        assert topics["/h16a/shared"] == "std_msgs/msg/Float64"
    finally:
        for bridge in bridges:
            bridge.close()
        for server in servers:
            server.stop()
    for server in servers:
        assert "Traceback" not in server.log, server.log
