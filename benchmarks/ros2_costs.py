"""What the ROS 2 adapter costs the server: start-up, binding, and publish() per message.

Run: ``.venv/bin/python -m benchmarks.ros2_costs [--singles 2000] [--repeats 3]`` (needs the
``ros2`` extra). Discovery stays on this host (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``,
domain 67). Prints a Markdown table:

* the adapter's start and close, the first publisher of a new type, ``create_publisher`` and
  ``subscribe`` (medians over 20 each);
* ``publish`` of one message (a field value or a whole message, without and with a local
  subscriber) and per message of a batch of 100, **next to rclpy's own ``publish`` of the
  same, already built message on the same node** (the same run's baseline: what converting
  a value into a message adds). Rounds of the two alternate; medians and p99 over all.

This was a test (tests/adapters/test_ros2_costs.py) that printed figures; figures belong here.
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

TWIST = {"linear": {"x": 1.0, "y": 2.0, "z": 3.0}, "angular": {"x": 4.0, "y": 5.0, "z": 6.0}}
CASES: tuple[tuple[str, str | None, Any], ...] = (
    ("std_msgs/msg/Float64", "data", 1.5),
    ("geometry_msgs/msg/Twist", "linear.x", 1.5),
    ("geometry_msgs/msg/Twist", None, TWIST),
)


def _us(seconds: float) -> str:
    return f"{seconds * 1e6:.1f}"


def _timed(action: Callable[[], Any]) -> float:
    t0 = time.perf_counter()
    action()
    return time.perf_counter() - t0


def _times(publish: Callable[[Any], None], msg: Any, n: int) -> None:
    for _ in range(n):
        publish(msg)


def _ignore(values: Sequence[Any]) -> None:
    """A local subscriber that takes the messages and does nothing with them."""


def binding_costs(domain: int) -> list[tuple[str, str]]:
    from rlbridge.adapters.base import QoS
    from rlbridge.adapters.ros2 import Ros2Adapter

    holder: list[Ros2Adapter] = []
    start = _timed(lambda: holder.append(Ros2Adapter("rlbridge_costs", domain_id=domain)))
    adapter = holder[0]
    try:
        first = _timed(lambda: adapter.create_publisher("/costs/p0", "geometry_msgs/msg/Pose",
                                                        "position.x", QoS()))
        pubs = [_timed(functools.partial(adapter.create_publisher, f"/costs/p{i}",
                                         "std_msgs/msg/Float64", "data", QoS()))
                for i in range(1, 21)]
        subs = [_timed(functools.partial(adapter.subscribe, f"/costs/s{i}",
                                         "std_msgs/msg/Float64", "data", QoS(), _ignore))
                for i in range(20)]
    finally:
        close = _timed(adapter.close)
    return [("adapter start", f"{start * 1e3:.1f} ms"),
            ("adapter close (20 publishers, 20 subscriptions)", f"{close * 1e3:.1f} ms"),
            ("first publisher of a new type", f"{first * 1e3:.2f} ms"),
            ("create_publisher, median of 20", f"{_us(statistics.median(pubs))} us"),
            ("subscribe, median of 20", f"{_us(statistics.median(subs))} us")]


def publish_costs(domain: int, singles: int, repeats: int) -> list[tuple[str, ...]]:
    from rclpy.qos import QoSProfile

    from rlbridge.adapters.base import QoS
    from rlbridge.adapters.ros2 import Ros2Adapter

    rows: list[tuple[str, ...]] = []
    with Ros2Adapter("rlbridge_publish_cost", domain_id=domain) as adapter:
        for n, (msg_type, field, value) in enumerate(CASES):
            for subscribed in (False, True):
                topic = f"/costs/pub{n}{'s' if subscribed else ''}"
                if subscribed:
                    adapter.subscribe(topic, msg_type, field, QoS(depth=1000), _ignore)
                pub = adapter.create_publisher(topic, msg_type, field, QoS(depth=1000))
                codec = adapter.catalog.channel(msg_type, field)
                cls, msg = codec.msg_cls, codec.encode(value)  # built once, outside the timing
                raw = adapter.node.create_publisher(cls, topic + "_raw", QoSProfile(depth=1000))
                if subscribed:
                    adapter.node.create_subscription(cls, topic + "_raw", _ignore,
                                                     QoSProfile(depth=1000))
                ours, theirs, batch_ours, batch_theirs = _alternate(
                    pub.publish, raw.publish, value, msg, singles, repeats)
                p99 = int(len(ours) * 0.99)
                rows.append((f"{msg_type} {field or '(whole)'}",
                             "local subscriber" if subscribed else "none",
                             f"{_us(statistics.median(ours))} / {_us(ours[p99])}",
                             f"{_us(statistics.median(theirs))} / {_us(theirs[p99])}",
                             f"{statistics.median(ours) / statistics.median(theirs):.2f}",
                             f"{_us(statistics.median(batch_ours))}",
                             f"{_us(statistics.median(batch_theirs))}"))
    return rows


def _alternate(ours_publish: Callable[[list[Any]], None], rclpy_publish: Callable[[Any], None],
               value: Any, msg: Any, singles: int, repeats: int
               ) -> tuple[list[float], list[float], list[float], list[float]]:
    """Rounds of the adapter's publish and rclpy's, alternating: (single times, sorted, each;
    then per-message times of batches of 100, each)."""
    ours: list[float] = []
    theirs: list[float] = []
    batch_ours: list[float] = []
    batch_theirs: list[float] = []
    ours_publish([value] * 100)  # warm up both
    for _ in range(100):
        rclpy_publish(msg)
    for _ in range(repeats):
        for _ in range(singles // repeats):
            ours.append(_timed(lambda: ours_publish([value])))
            theirs.append(_timed(lambda: rclpy_publish(msg)))
        batch_ours.append(_timed(lambda: ours_publish([value] * 100)) / 100)
        batch_theirs.append(_timed(lambda: _times(rclpy_publish, msg, 100)) / 100)
    return sorted(ours), sorted(theirs), batch_ours, batch_theirs


def main() -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    p.add_argument("--singles", type=int, default=2000, help="single publishes per case")
    p.add_argument("--repeats", type=int, default=4, help="alternating rounds per case")
    p.add_argument("--domain", type=int, default=67, help="ROS_DOMAIN_ID to use")
    args = p.parse_args()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.pop("ROS_STATIC_PEERS", None)
    print("| what | figure |\n| --- | --- |")
    for what, figure in binding_costs(args.domain):
        print(f"| {what} | {figure} |")
    print("\n| message | subscriber | adapter publish p50 / p99 (us) | rclpy publish p50 / "
          "p99 (us) | ratio p50 | adapter, batch of 100 (us/msg) | rclpy x100 (us/msg) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for row in publish_costs(args.domain, args.singles, args.repeats):
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
