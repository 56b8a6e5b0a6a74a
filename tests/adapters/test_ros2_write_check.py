"""The write-time check agrees with the server's check for ROS 2 message types too.

The schema in a ``TopicAck`` comes from the ROS 2 adapter's own msgspec types (built from the
installed message packages); for each value here the SDK's ``write`` must refuse exactly what
the server's validation refuses.
"""

from __future__ import annotations

from typing import Any

import pytest

from write_agreement import assert_write_check_agrees

pytest.importorskip("rclpy", reason="rclpy is not installed (pip install 'rlbridge-sdk[ros2]')")

CASES: list[tuple[str, str | None, list[Any]]] = [
    ("std_msgs/msg/Float32", "data", [1.0, 2, True, "1"]),
    ("std_msgs/msg/UInt64", "data", [0, 2**64 - 1, -1, 1.5]),
    ("std_msgs/msg/Char", "data", [0, 255, 256, "a"]),
    ("std_msgs/msg/Float64MultiArray", "data", [[1.0, 2], [], [1.0, "x"], (3.0,), 1.0]),
    ("std_msgs/msg/Float64MultiArray", None, [{"data": [1.0]}, {"layout": {"dim": []}},
                                              {"layout": {"data_offset": -1}}, {"nope": 1}]),
    ("geometry_msgs/msg/PoseStamped", None, [
        {"header": {"frame_id": "map", "stamp": {"sec": 1, "nanosec": 2}},
         "pose": {"position": {"x": 1}}},
        {"header": {"stamp": {"nanosec": -1}}},
        {"header": {"frame_id": 5}},
        {"pose": {"orientation": {"w": None}}}]),
]


@pytest.mark.parametrize(("msg_type", "field", "values"), CASES,
                         ids=[f"{t.rsplit('/', 1)[1]}-{f}" for t, f, _ in CASES])
def test_write_check_agrees_with_the_ros2_server(msg_type: str, field: str | None,
                                                 values: list[Any]) -> None:
    from rlbridge.adapters.ros2_types import MessageCatalog

    spec = MessageCatalog().resolve(msg_type, field)
    assert spec.msg_type == msg_type
    assert_write_check_agrees(spec, field, values)
