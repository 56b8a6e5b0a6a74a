"""What the ROS 2 adapter costs the server: start-up, binding, and publish() per message.

Figures are printed (``pytest -s tests/adapters/test_ros2_costs.py``) as a baseline for the
benchmarks (``rlbridge bench ros2`` for the figures with a same-run baseline). No timing is
asserted: on a shared machine any bound fails for reasons that are not bugs. The tests check
that each operation works at volume (every binding made, every publish accepted).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any

import pytest
from contract import Collector

from rlbridge.adapters.base import QoS

ros2 = pytest.importorskip(
    "rlbridge.adapters.ros2",
    reason="rclpy is not installed (pip install 'rlbridge-sdk[ros2]')",
    exc_type=ImportError,
)

pytestmark = [pytest.mark.ros2, pytest.mark.timeout(60)]

TWIST = {"linear": {"x": 1.0, "y": 2.0, "z": 3.0}, "angular": {"x": 4.0, "y": 5.0, "z": 6.0}}


def _us(seconds: float) -> str:
    return f"{seconds * 1e6:.1f} us"


def _timed(action: Callable[[], Any]) -> tuple[float, Any]:
    t0 = time.perf_counter()
    result = action()
    return time.perf_counter() - t0, result


def test_start_up_and_binding_costs(ros_env: int, unique_topic: Callable[[str], str]) -> None:
    start, adapter = _timed(lambda: ros2.Ros2Adapter("rlbridge_costs", domain_id=ros_env))
    try:
        first_pub, _ = _timed(
            lambda: adapter.create_publisher(unique_topic("p0"), "geometry_msgs/msg/Pose",
                                             "position.x", QoS())
        )
        pubs = [
            _timed(lambda i=i: adapter.create_publisher(unique_topic(f"p{i}"),
                                                        "std_msgs/msg/Float64", "data", QoS()))[0]
            for i in range(1, 21)
        ]
        subs = [
            _timed(lambda i=i: adapter.subscribe(unique_topic(f"s{i}"), "std_msgs/msg/Float64",
                                                 "data", QoS(), Collector()))[0]
            for i in range(20)
        ]
    finally:
        close, _ = _timed(adapter.close)
    print(
        f"\n[ros2] adapter start {start * 1e3:.1f} ms, close (20 pubs + 20 subs) "
        f"{close * 1e3:.1f} ms; first publisher of a new type {first_pub * 1e3:.2f} ms; "
        f"create_publisher p50 {_us(statistics.median(pubs))}, subscribe p50 "
        f"{_us(statistics.median(subs))}"
    )
    assert len(pubs) == len(subs) == 20


@pytest.mark.parametrize(
    ("msg_type", "field", "value"),
    [
        ("std_msgs/msg/Float64", "data", 1.5),
        ("geometry_msgs/msg/Twist", "linear.x", 1.5),
        ("geometry_msgs/msg/Twist", None, TWIST),
    ],
    ids=["Float64.data", "Twist.linear.x", "Twist-whole"],
)
@pytest.mark.parametrize("subscribed", [False, True], ids=["no-sub", "local-sub"])
def test_publish_cost_per_message(
    ros_env: int,
    unique_topic: Callable[[str], str],
    msg_type: str,
    field: str | None,
    value: Any,
    subscribed: bool,
) -> None:
    with ros2.Ros2Adapter("rlbridge_publish_cost", domain_id=ros_env) as adapter:
        topic = unique_topic("cost")
        if subscribed:
            adapter.subscribe(topic, msg_type, field, QoS(depth=1000), Collector())
        pub = adapter.create_publisher(topic, msg_type, field, QoS(depth=1000))
        pub.publish([value] * 100)  # warm up
        singles = []
        for _ in range(2000):
            t0 = time.perf_counter()
            pub.publish([value])
            singles.append(time.perf_counter() - t0)
        batches = []
        for _ in range(20):
            t0 = time.perf_counter()
            pub.publish([value] * 100)
            batches.append((time.perf_counter() - t0) / 100)
    singles.sort()
    reader = "local subscriber" if subscribed else "no subscriber"
    print(
        f"\n[ros2] publish {msg_type} {field or 'whole'} ({reader}): "
        f"batch of 1 p50 {_us(statistics.median(singles))} p99 "
        f"{_us(singles[int(len(singles) * 0.99)])}; batch of 100 "
        f"{_us(statistics.median(batches))}/msg"
    )
    assert len(singles) == 2000
