"""The child processes of ``rlbridge bench ros2`` (see :mod:`rlbridge.bench.ros2`).

Senders and receivers of the rows, each run as ``worker_main`` role in a process of its own: a
plain rclpy node (``SingleThreadedExecutor`` in a thread, one callback per message: what a ROS
user writes) or an SDK client of the bridge server. Senders publish warm-up values (-1) every
10 ms until ``go``; receivers report ``joined`` at the first one and ignore negative values.
rclpy is imported inside the roles, so importing this module needs no ROS.
"""

from __future__ import annotations

import importlib
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from rlbridge.bench.common import (
    STARTUP_S,
    Control,
    Params,
    Role,
    Tally,
    emit,
    flood,
    hold,
    paced,
    wait_for_go,
)
from rlbridge.bench.throughput import _write_loop

MSG_TYPE = "std_msgs/msg/Float64"
DEPTH = 10


@contextmanager
def _ros_node(name: str) -> Iterator[Any]:
    """A plain rclpy node with its executor spun in a thread: what a ROS user writes."""
    with warnings.catch_warnings():  # lark (under rosidl_generator_py) imports sre_parse
        warnings.simplefilter("ignore", DeprecationWarning)
        importlib.import_module("rosidl_generator_py")
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    context = Context()
    context.init(args=[])
    node = Node(name, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    # Stopped by flag, then shut down after the join: ``executor.shutdown()`` under a running
    # spin() can destroy the wait's guard condition while the thread rebuilds its wait set,
    # and that thread then waits forever (the adapter's close() had the same race).
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set() and context.ok():
            executor.spin_once(timeout_sec=0.05)

    spinner = threading.Thread(target=spin, name="bench-ros-spin", daemon=True)
    spinner.start()
    try:
        yield node
    finally:
        stop.set()
        spinner.join(2.0)
        executor.shutdown(timeout_sec=0)
        node.destroy_node()
        context.try_shutdown()


def _qos(reliability: str) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=DEPTH, durability=DurabilityPolicy.VOLATILE,
        reliability=(ReliabilityPolicy.BEST_EFFORT if reliability == "best_effort"
                     else ReliabilityPolicy.RELIABLE))


def _send(control: Control, params: Params, write: Callable[[float], object],
          write_flood: Callable[[], tuple[int, float]]) -> None:
    """The sender's part after set-up: warm up until ``go``, then pace or flood, report."""
    emit("ready")
    wait_for_go(control, lambda: write(-1.0))
    if params["mode"] == "latency":
        sent, t0, t1 = paced(lambda t: write(float(t)), float(params["rate_hz"]),
                             int(params["count"]))
    else:
        sent, t0 = write_flood()
        t1 = time.monotonic()
    emit("sent", sent=sent, t_start=t0, t_end=t1)
    hold(control)


def ros_publisher(params: Params) -> None:
    """An rclpy publisher node; ``rclpy.Publisher.publish`` per value."""
    control = Control()
    with _ros_node("rlbridge_bench_pub") as node:
        cls = importlib.import_module("std_msgs.msg").Float64
        pub = node.create_publisher(cls, params["topic"], _qos("reliable"))

        def write(value: float) -> None:
            pub.publish(cls(data=value))

        msg = cls(data=1.0)

        def write_flood() -> tuple[int, float]:
            sent, t0, _ = flood(lambda: pub.publish(msg), int(params["count"]),
                                float(params["seconds"]))
            return sent, t0

        _send(control, params, write, write_flood)


def sdk_publisher(params: Params) -> None:
    """An SDK publisher; ``write`` per value (flow-controlled by its ring in a flood)."""
    from rlbridge.client.bridge import Bridge

    control = Control()
    buffer = 1 << 16
    bridge = Bridge.connect(params["host"], int(params["port"]), name="bench-ros2-pub",
                            nodelay=True)
    out = bridge.publish(params["topic"], MSG_TYPE, "data", transport=params["transport"],
                         buffer_size=buffer)

    def write_flood() -> tuple[int, float]:
        sent, t0 = _write_loop(out, 1, buffer // 2, int(params["count"]),
                               float(params["seconds"]), 0.0)
        bridge.send(wait=True)
        return sent, t0

    _send(control, params, out.write, write_flood)


def _receive(control: Control, params: Params, joined: threading.Event, tally: Tally) -> None:
    """The receiver's part after set-up: ``joined`` at the first warm-up, then the tally."""
    emit("ready")
    if not joined.wait(STARTUP_S):
        raise TimeoutError("no warm-up value arrived (discovery did not match the endpoints)")
    emit("joined")
    while not tally.done(time.monotonic()):
        time.sleep(0.005)
    tally.report()


def _on_value(value: float, joined: threading.Event, tally: Tally, latency: bool) -> None:
    if value < 0:
        joined.set()
    else:
        if latency:
            tally.samples.append(time.time_ns() - int(value))
        tally.add(1, time.monotonic())


def ros_subscriber(params: Params) -> None:
    """An rclpy subscriber node: one callback per message on the executor thread."""
    control = Control()
    tally = Tally(control, float(params["idle_s"]))
    joined = threading.Event()
    latency = params["mode"] == "latency"
    with _ros_node("rlbridge_bench_sub") as node:
        cls = importlib.import_module("std_msgs.msg").Float64
        node.create_subscription(cls, params["topic"],
                                 lambda msg: _on_value(msg.data, joined, tally, latency),
                                 _qos(params["reliability"]))
        _receive(control, params, joined, tally)


def sdk_subscriber(params: Params) -> None:
    """An SDK subscriber: blocking reads in a thread of its own, as a control loop would."""
    from rlbridge.client.bridge import Bridge

    control = Control()
    tally = Tally(control, float(params["idle_s"]))
    joined = threading.Event()
    latency = params["mode"] == "latency"
    bridge = Bridge.connect(params["host"], int(params["port"]), name="bench-ros2-sub",
                            nodelay=True)
    ch = bridge.subscribe(params["topic"], MSG_TYPE, "data", transport=params["transport"],
                          blocking=True, buffer_size=1 << 16)
    stop = threading.Event()

    def read_loop() -> None:
        while not stop.is_set():
            try:
                values = [ch.read(0.05), *ch.read_many()]
            except TimeoutError:
                continue
            for value in values:
                _on_value(value, joined, tally, latency)

    reader = threading.Thread(target=read_loop, name="bench-ros2-read", daemon=True)
    reader.start()
    try:
        _receive(control, params, joined, tally)
    finally:
        stop.set()
        reader.join(1.0)


ROLES: dict[str, Role] = {"ros_publisher": ros_publisher, "sdk_publisher": sdk_publisher,
                          "ros_subscriber": ros_subscriber, "sdk_subscriber": sdk_subscriber}
