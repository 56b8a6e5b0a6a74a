#!/usr/bin/env python3
"""The pan-tilt vision node as a plain ROS 2 node: rclpy only, nothing from rlbridge.

It publishes the bearing of a target moving on a Lissajous path as ``std_msgs/msg/Float64``
set-points at the camera's frame rate (30 Hz) on ``/pan_tilt/pan/setpoint`` and
``/pan_tilt/tilt/setpoint``, and listens to what the embedded controller sends back through the
bridge: ``/pan_tilt/{pan,tilt}/angle`` (Float64, 50 Hz), ``/pan_tilt/status`` (String, on change)
and ``/pan_tilt/diagnostics`` (String, JSON, 5 Hz). One line a second says what it sees.

Run it next to a bridge server on ROS 2 and the controller (three terminals)::

    rlbridge serve --adapter ros2 --nodelay
    rlbridge demo --role controller            # or: python examples/pan_tilt/controller.py
    python examples/pan_tilt/vision_ros2.py --seconds 20

Set-points use the sensor-data QoS (best effort, shallow history): a late set-point is worth
nothing once the next frame exists, which is also why the bridge carries them over UDP.

Without rclpy it prints why and exits with status 0, so scripts that try every example skip it.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import math
import signal
import sys
import time
import warnings
from typing import Any

try:
    with warnings.catch_warnings():
        # lark (under rosidl_generator_py) imports the deprecated sre_parse module.
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        importlib.import_module("rosidl_generator_py")
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import Float64, String
except ImportError as exc:
    print(f"vision_ros2.py: skipped: rclpy is not available ({exc}); "
          "install it with: pip install -e '.[ros2]' in the rlbridge checkout", file=sys.stderr)
    sys.exit(0)

AXES = ("pan", "tilt")


class VisionNode(Node):  # type: ignore[misc,unused-ignore]  # Any where rclpy is missing
    """30 Hz set-points out; angles, status and diagnostics in."""

    def __init__(self, context: Context, args: argparse.Namespace) -> None:
        super().__init__("pan_tilt_vision", context=context)
        ns = args.namespace.rstrip("/")
        self.args = args
        self.t0 = time.monotonic()
        self.frames = 0
        self.angles: dict[str, float] = dict.fromkeys(AXES, math.nan)
        self.angle_count = dict.fromkeys(AXES, 0)
        self.statuses: list[tuple[float, str]] = []
        self.diagnostics: dict[str, Any] = {}
        self.setpoint = (math.nan, math.nan)
        self.pubs = {axis: self.create_publisher(Float64, f"{ns}/{axis}/setpoint",
                                                 qos_profile_sensor_data) for axis in AXES}
        for axis in AXES:
            self.create_subscription(Float64, f"{ns}/{axis}/angle",
                                     lambda msg, a=axis: self.on_angle(a, msg.data),
                                     qos_profile_sensor_data)
        reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        self.create_subscription(String, f"{ns}/status", self.on_status, reliable)
        self.create_subscription(String, f"{ns}/diagnostics", self.on_diagnostics, reliable)
        self.create_timer(1.0 / args.rate, self.on_frame)

    def now(self) -> float:
        return time.monotonic() - self.t0

    def on_frame(self) -> None:
        t = self.now()
        a = self.args
        if a.dropout_for > 0 and a.dropout_at <= t < a.dropout_at + a.dropout_for:
            return  # the target left the image: no set-point
        pan = 0.8 * math.sin(2 * math.pi * 0.2 * t)
        tilt = 0.4 * math.sin(2 * math.pi * 0.3 * t + 0.5)
        for axis, value in zip(AXES, (pan, tilt), strict=True):
            msg = Float64()
            msg.data = value
            self.pubs[axis].publish(msg)
        self.setpoint = (pan, tilt)
        self.frames += 1

    def on_angle(self, axis: str, value: float) -> None:
        self.angles[axis] = value
        self.angle_count[axis] += 1

    def on_status(self, msg: Any) -> None:
        self.statuses.append((self.now(), msg.data))
        print(f"t={self.now():6.2f}s controller status: {msg.data}", flush=True)

    def on_diagnostics(self, msg: Any) -> None:
        with contextlib.suppress(ValueError):  # not JSON: not our controller; ignore it
            self.diagnostics = json.loads(msg.data)

    def line(self) -> str:
        d = self.diagnostics
        sp, an = self.setpoint, self.angles
        p99 = d.get("late_p99_us")
        loop = f"loop p99 {p99 / 1e3:.2f} ms" if isinstance(p99, float | int) else "no diagnostics"
        return (f"t={self.now():6.2f}s frames {self.frames} | pan sp {_rad(sp[0])} angle "
                f"{_rad(an['pan'])} | tilt sp {_rad(sp[1])} angle {_rad(an['tilt'])} | "
                f"angles received {sum(self.angle_count.values())} | controller "
                f"{d.get('state', '-')} link {d.get('link', '-')} {loop}")


def _rad(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:+.3f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=0.0, help="0: until Ctrl-C")
    parser.add_argument("--rate", type=float, default=30.0, help="frame rate (Hz)")
    parser.add_argument("--namespace", default="/pan_tilt")
    parser.add_argument("--dropout-at", type=float, default=4.0)
    parser.add_argument("--dropout-for", type=float, default=0.5, help="0: never")
    parser.add_argument("--report", help="write what was seen as JSON to this file")
    args = parser.parse_args()

    stop = False

    def request_stop(_signum: int, _frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)

    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = VisionNode(context, args)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        next_line = 1.0
        while not stop and (args.seconds <= 0 or node.now() < args.seconds):
            executor.spin_once(timeout_sec=0.05)
            if node.now() >= next_line:
                next_line += 1.0
                print(node.line(), flush=True)
        if args.report:
            with open(args.report, "w") as f:
                json.dump({"frames": node.frames, "angles_received": node.angle_count,
                           "statuses": node.statuses, "diagnostics": node.diagnostics}, f)
    finally:
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
