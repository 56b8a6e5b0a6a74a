"""No uncounted loss on the ROS side: the two floods of issue #16, every lost value counted.

In a private network namespace (:mod:`reach_netns`), with real rclpy nodes:

* node -> client: an rclpy node publishes a burst as fast as it can; the server's ROS
  subscription has the default depth (10), so its queue overflows while the executor thread
  is busy. Once the burst's last message has reached the SDK, every message after the first
  one the server took is either delivered to the SDK or counted in ``ros_lost`` (sequence
  gaps), in ``rlbridge stats`` and ``health()``: exactly, the sum is the number published.
* client -> node: the SDK floods a TCP channel; the server hands each accepted value to
  rclpy (or counts ROS's refusal in ``ros_lost``); the slow node receives each or sees its
  gap (its own queue of 10 overflowing), counted by the node from the same sequence numbers.

The assertions are sums that must hold whatever the timing; how much was lost is printed.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator

import pytest
from reach_netns import World, world

from rlbridge.client.bridge import Bridge
from rlbridge.client.channels.incoming import IncomingChannel
from waiting import wait_until

pytestmark = [pytest.mark.ros2, pytest.mark.netem, pytest.mark.timeout(240)]

INT64 = "std_msgs/msg/Int64"
N = 20_000


@pytest.fixture(scope="module")
def flood_world(tmp_path_factory: pytest.TempPathFactory) -> Iterator[World]:
    # A flood saturates a 2-core machine on purpose; these tests count values, and the
    # watchdog (600 ms by default, tested in tests/server) must not end the session meanwhile.
    with world("flood", tmp_path_factory.mktemp("ros_log"),
               server_options=("--timeout-ms", "10000")) as made:
        yield made


@pytest.fixture
def sdk(flood_world: World) -> Iterator[Bridge]:
    bridge = flood_world.connect("flood-sdk")
    try:
        yield bridge
    finally:
        bridge.close()


def channel_stats(bridge: Bridge, channel: int) -> dict[str, int]:
    return bridge.server_stats()["session"]["channels"][str(channel)]


def read_until(ch: IncomingChannel, last: int, received: list[int]) -> float:
    """Read into ``received`` until ``last`` arrives (the publisher's final message: a
    KEEP_LAST queue never drops its newest, so it always does, and after it every earlier
    message of that publisher is delivered or counted). Not "until quiet": a reliable DDS
    writer repairs a sample lost in transport at its next heartbeat, up to 3 s later with
    Fast DDS's defaults, and what is still in flight then is neither delivered nor lost yet.
    Returns the longest stop between two arrivals (seconds), for the printout."""
    at = time.monotonic()
    longest = 0.0

    def last_came() -> bool:
        nonlocal at, longest
        if received[-1] == last:
            return True
        got = ch.read_many()
        if not got:
            with contextlib.suppress(TimeoutError):
                got = [ch.read(timeout=1.0)]
        if got:
            now = time.monotonic()
            longest, at = max(longest, now - at), now
            received.extend(got)
        return received[-1] == last

    wait_until(last_came, lambda: f"{last} ({len(received)} values came)", timeout=120,
               interval=0)
    return longest


def test_node_to_client_flood_every_loss_counted(flood_world: World, sdk: Bridge) -> None:
    ch = sdk.subscribe("/flood/down", INT64, transport="tcp", blocking=True,
                       buffer_size=4 * N)
    peer = flood_world.peer("flood", "/flood/down", str(N), watch=r"^probes (\d+) refused (\d+)")
    try:
        first = ch.read(timeout=60)  # a probe: the server's subscription is matched
        assert first < 0
        assert peer.proc.stdin is not None
        peer.proc.stdin.write("go\n")
        peer.proc.stdin.flush()
        done = peer.wait_ready()
        probes, refused = int(done.group(1)), int(done.group(2))
        received = [first]
        stop = read_until(ch, N - 1, received)
    finally:
        peer.stop()
    stats = channel_stats(sdk, ch.channel_id)
    expected = (probes + first) + N  # probes after the first one (-k), then the burst
    lost = stats["ros_lost"]
    print(f"node->client: {N} published ({refused} refused by rmw and published again), "
          f"{len(received) - 1} delivered, {lost} lost in the server's ROS subscription queue "
          f"(depth 10); longest stop in the burst {stop:.2f} s")
    assert ch.health().overwritten == 0
    assert stats["dropped"] == 0
    assert (len(received) - 1) + lost == expected
    if lost:  # the RosLoss report, once per heartbeat period
        wait_until(lambda: ch.health().ros_lost == lost, f"the RosLoss report of {lost}",
                   interval=0.05)
    else:
        assert ch.health().ros_lost in (-1, 0)
    totals = sdk.server_stats()["server"]
    assert totals["ros_lost"] >= lost


def test_client_to_node_flood_every_loss_counted(flood_world: World, sdk: Bridge) -> None:
    node = flood_world.peer("count", "/flood/up", "10", str(N - 1), watch=r"^first (-?\d+)")
    out = sdk.publish("/flood/up", INT64, transport="tcp", buffer_size=4 * N)
    try:
        probed: list[int] = []

        def probe() -> None:
            probed.append(-len(probed) - 1)
            out.write(probed[-1])

        wait_until(lambda: node.match is not None, "the node to take a probe (discovery)",
                   timeout=60, interval=0.05, between=probe)
        probes = len(probed)
        first = int(node.wait_ready().group(1))
        for i in range(N):
            out.write(i)
        sdk.send(wait=True)
        assert node.proc.wait(120) == 0, node.log
    finally:
        node.stop()
    result = json.loads(node.lines[-1])
    stats = channel_stats(sdk, out.channel_id)
    handed = stats["values_in"] - stats["ros_lost"]
    print(f"client->node: {N} written, {stats['values_in']} accepted by the server, "
          f"{stats['ros_lost']} refused by ROS, {result['received']} received by the node, "
          f"{result['gaps']} lost in the node's queue (depth 10)")
    assert out.statistics().overwritten == 0
    assert stats["values_in"] == probes + N
    # Every value after the node's first: received by the node, or a gap the node counted.
    after_first = (probes + first) + N
    assert (result["received"] - 1) + result["gaps"] + stats["ros_lost"] == after_first
    assert handed == stats["values_in"] - stats["ros_lost"]
