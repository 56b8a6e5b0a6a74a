"""The middleware side's "image processing" node: set-points at the camera's frame rate.

A real JIWIY setup finds the object in each camera frame and publishes where the camera should
point. Here the object moves on a Lissajous path and the node publishes its bearing at 30 Hz,
one ``std_msgs/msg/Float64`` per axis. A *dropout* (the object leaves the image) stops the
stream for a while, which is what the controller's ``safe`` state is for.

The node is written against :class:`~rlbridge.adapters.base.MiddlewareAdapter`, the same
interface the bridge server uses, so it is an ordinary node of whichever middleware the server
runs: the in-process bus, or ROS 2 (then it is a publisher on the ROS graph, and
``ros2 topic echo /pan_tilt/pan/setpoint`` shows its output). ``examples/pan_tilt/vision_ros2.py``
is the same node written with plain rclpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rlbridge.adapters.base import MiddlewareAdapter, Publisher, QoS
from rlbridge.csp.process import Code
from rlbridge.csp.timer import Timed
from rlbridge.demo.monitor import Trace
from rlbridge.demo.topics import AXES, FLOAT64, Topics

FRAME_RATE_HZ = 30.0


@dataclass(frozen=True, slots=True)
class Lissajous:
    """The target's bearing (pan, tilt) in radians at time ``t``: a 2:3 Lissajous figure."""

    pan_amplitude: float = 0.8
    pan_hz: float = 0.2
    tilt_amplitude: float = 0.4
    tilt_hz: float = 0.3
    phase: float = 0.5

    def position(self, t: float) -> tuple[float, float]:
        return (self.pan_amplitude * math.sin(2.0 * math.pi * self.pan_hz * t),
                self.tilt_amplitude * math.sin(2.0 * math.pi * self.tilt_hz * t + self.phase))


@dataclass(frozen=True, slots=True)
class Dropout:
    """The target is not seen from ``start`` for ``length`` seconds (``length`` 0: never)."""

    start: float = 2.0
    length: float = 0.5

    def active(self, t: float) -> bool:
        return self.length > 0 and self.start <= t < self.start + self.length


class VisionNode:
    """Publishes the target's bearing at the frame rate; see the module docstring.

    Frames are released by a :class:`~rlbridge.csp.timer.Timed` process (absolute deadlines,
    so 30 Hz stays 30 Hz). ``start`` starts its thread, ``close`` stops and joins it, then
    releases the publishers.
    """

    def __init__(self, adapter: MiddlewareAdapter, trace: Trace, *, topics: Topics | None = None,
                 target: Lissajous | None = None, rate_hz: float = FRAME_RATE_HZ,
                 start_after: float = 0.5, dropout: Dropout | None = None) -> None:
        t = topics or Topics()
        self.trace = trace
        self.target = target or Lissajous()
        self.start_after = start_after
        self.dropout = dropout or Dropout(length=0.0)
        self.frames = 0
        # Best effort, depth 1: a late set-point is worth nothing once the next frame exists.
        qos = QoS("best_effort", 1)
        pubs: list[Publisher] = []
        try:
            pubs.extend(adapter.create_publisher(t.setpoint(axis), FLOAT64, "data", qos)
                        for axis in AXES)
        except BaseException:
            for pub in pubs:
                pub.close()
            raise
        self._pan, self._tilt = pubs
        self._process = Timed(Code(self._frame, name="vision frame"), 1.0 / rate_hz,
                              name="vision")

    def _frame(self) -> None:
        t = self.trace.now()
        if t < self.start_after or self.dropout.active(t):
            return
        pan, tilt = self.target.position(t)
        self._pan.publish([pan])
        self._tilt.publish([tilt])
        self.frames += 1
        self.trace.add_setpoint(t, pan, tilt)

    def start(self) -> VisionNode:
        self._process.start()
        return self

    def close(self, timeout: float = 5.0) -> None:
        """Stop publishing, join the frame thread, release the publishers."""
        self._process.stop()
        try:
            if not self._process.join(timeout):
                raise TimeoutError(f"the vision node did not stop within {timeout} s")
        finally:
            self._pan.close()
            self._tilt.close()
