#!/usr/bin/env python3
"""A plain rclpy node in a process of its own: the "other ROS node" of the ROS 2 tests.

It deliberately imports nothing from rlbridge (its message <-> dict code is its own, a few
lines of generic reflection), so a test passing through it checks the adapter against rclpy,
not against itself.

Modes
-----
``serve`` (default)
    Read JSON requests from stdin, one a line: ``{"id": 1, "op": "pub", ...}``; answer each
    with ``{"id": 1, "ok": result}`` or ``{"id": 1, "error": "..."}``. Messages received by a
    subscription are written as ``{"event": "msg", "sub": handle, "value": ...}``. Ops: ``pub``,
    ``sub`` (topic, type, field, reliability, depth), ``publish`` (handle, values), ``stream``
    (handle, rate, count: Float64 stamps ``time.perf_counter()`` at ``rate`` Hz, in a thread),
    ``close`` (handle), ``matched`` (handle), ``topics``, ``get_params`` (node, names), ``quit``.
``latency [--rate HZ] [--count N] [--depth D]``
    The node-to-node baseline: start a ``latency-pub`` process publishing Float64 stamped with
    ``time.perf_counter()`` (CLOCK_MONOTONIC, the same clock in every process) at ``rate`` Hz,
    subscribe here, print p50/p99/max latency in microseconds as one JSON line.
``release``
    Print which rclpy this interpreter has, as one JSON line: its distribution and version
    (``ros-rclpy`` 9.1 for the current wheels, 7.1 for Jazzy's), the RMW, the Python version.

Discovery scope comes from the environment (``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE``)
which the tests set; run it by hand with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import os
import statistics
import subprocess
import sys
import threading
import time
import warnings
from typing import Any

with warnings.catch_warnings():
    # lark-parser (under rosidl_generator_py) imports the deprecated sre_parse.
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    importlib.import_module("rosidl_generator_py")

import rclpy
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

LATENCY_TOPIC = "/rlbridge_latency"


def message_class(name: str) -> Any:
    package, _, type_name = name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), type_name)


def to_plain(value: Any) -> Any:
    if hasattr(value, "get_fields_and_field_types"):
        return {k: to_plain(getattr(value, k)) for k in value.get_fields_and_field_types()}
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, list | tuple):
        return [to_plain(v) for v in value]
    if isinstance(value, bytes) and len(value) == 1:
        return value[0]
    return value


def set_field(msg: Any, name: str, value: Any) -> None:
    """Set one field from its plain value: floats widened, octets as 1-byte ``bytes``."""
    type_name = msg.get_fields_and_field_types()[name]
    current = getattr(msg, name)
    if hasattr(current, "get_fields_and_field_types"):
        fill(current, value)
    elif isinstance(value, list) and "/" in type_name:  # sequence or array of messages
        item_type = type_name.split("<")[-1].split(",")[0].split("[")[0].rstrip(">")
        package, _, item_name = item_type.partition("/")
        items = []
        for item in value:
            m = message_class(f"{package}/msg/{item_name}")()
            fill(m, item)
            items.append(m)
        setattr(msg, name, items)
    elif type_name in ("double", "float"):
        setattr(msg, name, float(value))
    elif type_name == "octet":
        setattr(msg, name, bytes([value]))
    else:
        setattr(msg, name, value)


def fill(msg: Any, values: dict[str, Any]) -> None:
    for key, value in values.items():
        set_field(msg, key, value)


def build(cls: Any, field: str | None, value: Any) -> Any:
    msg = cls()
    if field is None:
        fill(msg, value)
        return msg
    *head, last = field.split(".")
    target = msg
    for name in head:
        target = getattr(target, name)
    set_field(target, last, value)
    return msg


def read(msg: Any, field: str | None) -> Any:
    if field is None:
        return to_plain(msg)
    value = msg
    for name in field.split("."):
        value = getattr(value, name)
    return to_plain(value)


def _spin_until(executor: Any, stop: threading.Event) -> None:
    """Spin until ``stop``; the caller joins, then shuts the executor down.

    ``executor.shutdown()`` under a running ``spin()`` can destroy the guard condition while the
    thread rebuilds its wait set; the thread then waits forever (the adapter's close() race).
    """
    with contextlib.suppress(ExternalShutdownException):
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)


def qos(request: dict[str, Any]) -> QoSProfile:
    reliability = (
        ReliabilityPolicy.BEST_EFFORT
        if request.get("reliability") == "best_effort"
        else ReliabilityPolicy.RELIABLE
    )
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(request.get("depth", 1000)),
        reliability=reliability,
        durability=DurabilityPolicy.VOLATILE,
    )


class Peer:
    """The ``serve`` mode: one node, one executor thread, requests on stdin."""

    def __init__(self) -> None:
        self.context = Context()
        self.context.init(args=[])
        self.node = Node("rlbridge_test_peer", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.out_lock = threading.Lock()
        self.endpoints: dict[int, Any] = {}
        self.bindings: dict[int, tuple[Any, str | None]] = {}
        self.next_handle = 1
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.spin, daemon=True)
        self.thread.start()

    def spin(self) -> None:
        """Until ``stop``; shutdown() only after the join (see ``_spin_until``)."""
        _spin_until(self.executor, self.stop)

    def emit(self, obj: dict[str, Any]) -> None:
        line = json.dumps(obj)
        with self.out_lock:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()

    def handle(self, request: dict[str, Any]) -> Any:
        op = request["op"]
        if op in ("pub", "sub"):
            cls = message_class(request["type"])
            handle = self.next_handle
            self.next_handle += 1
            field = request.get("field")
            if op == "pub":
                self.endpoints[handle] = self.node.create_publisher(
                    cls, request["topic"], qos(request)
                )
            else:

                def on_message(msg: Any, handle: int = handle, field: str | None = field) -> None:
                    self.emit({"event": "msg", "sub": handle, "value": read(msg, field)})

                self.endpoints[handle] = self.node.create_subscription(
                    cls, request["topic"], on_message, qos(request)
                )
            self.bindings[handle] = (cls, field)
            return handle
        if op == "publish":
            cls, field = self.bindings[request["handle"]]
            publisher = self.endpoints[request["handle"]]
            for value in request["values"]:
                publisher.publish(build(cls, field, value))
            return len(request["values"])
        if op == "stream":
            publisher = self.endpoints[request["handle"]]
            cls, _ = self.bindings[request["handle"]]
            threading.Thread(
                target=stream, args=(publisher, cls, request["rate"], request["count"]),
                daemon=True,
            ).start()
            return True
        if op == "close":
            endpoint = self.endpoints.pop(request["handle"])
            if hasattr(endpoint, "publish"):
                self.node.destroy_publisher(endpoint)
            else:
                self.node.destroy_subscription(endpoint)
            return True
        if op == "matched":
            endpoint = self.endpoints[request["handle"]]
            if hasattr(endpoint, "publish"):
                return endpoint.get_subscription_count()
            return endpoint.get_publisher_count()
        if op == "topics":
            return [[n, t] for n, t in self.node.get_topic_names_and_types()]
        if op == "get_params":
            return self.get_params(request["node"], request["names"])
        raise ValueError(f"unknown op {op!r}")

    def get_params(self, node: str, names: list[str]) -> list[Any]:
        """What ``ros2 param get`` does: call the node's GetParameters service."""
        srv = importlib.import_module("rcl_interfaces.srv")
        client = self.node.create_client(srv.GetParameters, f"{node}/get_parameters")
        try:
            if not client.wait_for_service(timeout_sec=10.0):
                raise TimeoutError(f"{node}/get_parameters did not appear")
            done = threading.Event()
            future = client.call_async(srv.GetParameters.Request(names=names))
            future.add_done_callback(lambda _: done.set())
            if not done.wait(10.0):
                raise TimeoutError("GetParameters did not answer")
            result = future.result()
            assert result is not None
            return [
                {1: v.bool_value, 2: v.integer_value, 3: v.double_value, 4: v.string_value}.get(
                    v.type
                )
                for v in result.values
            ]
        finally:
            self.node.destroy_client(client)

    def serve(self) -> None:
        for line in sys.stdin:
            if not line.strip():
                continue
            request = json.loads(line)
            if request["op"] == "quit":
                break
            try:
                self.emit({"id": request["id"], "ok": self.handle(request)})
            except Exception as exc:  # report to the test, keep serving
                self.emit({"id": request["id"], "error": f"{type(exc).__name__}: {exc}"})
        self.stop.set()
        self.thread.join(5.0)
        self.executor.shutdown(timeout_sec=0)
        self.node.destroy_node()
        self.context.try_shutdown()


def stream(publisher: Any, cls: Any, rate: float, count: int) -> None:
    """Publish ``count`` Float64 stamped with perf_counter at ``rate`` Hz (absolute schedule)."""
    period = 1.0 / rate
    start = time.perf_counter()
    for i in range(count):
        delay = start + i * period - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        msg = cls()
        msg.data = time.perf_counter()
        publisher.publish(msg)


def latency_pub(rate: float, count: int, depth: int) -> None:
    context = Context()
    context.init(args=[])
    node = Node("rlbridge_latency_pub", context=context)
    cls = message_class("std_msgs/msg/Float64")
    publisher = node.create_publisher(cls, LATENCY_TOPIC, qos({"depth": depth}))
    deadline = time.monotonic() + 10.0
    while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.2)  # let the subscriber's side of the match settle too
    stream(publisher, cls, rate, count)
    time.sleep(0.2)
    node.destroy_node()
    context.try_shutdown()


def latency(rate: float, count: int, depth: int) -> None:
    """Node-to-node latency of Float64 at ``rate`` Hz between two plain rclpy processes.

    Both sides use reliable KEEP_LAST(``depth``); a subscriber that falls behind by more than
    ``depth`` messages loses the oldest, which shows as ``received < sent``.
    """
    context = Context()
    context.init(args=[])
    node = Node("rlbridge_latency_sub", context=context)
    samples: list[float] = []
    done = threading.Event()

    def on_message(msg: Any) -> None:
        samples.append(time.perf_counter() - msg.data)
        if len(samples) >= count:
            done.set()

    node.create_subscription(message_class("std_msgs/msg/Float64"), LATENCY_TOPIC, on_message,
                             qos({"depth": depth}))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    stop = threading.Event()
    spinner = threading.Thread(target=_spin_until, args=(executor, stop), daemon=True)
    spinner.start()
    publisher = subprocess.Popen(
        [sys.executable, __file__, "latency-pub", "--rate", str(rate), "--count", str(count),
         "--depth", str(depth)]
    )
    publisher.wait(count / rate + 15.0)  # it lingers 0.2 s after its last message
    done.wait(1.0)
    stop.set()
    spinner.join(5.0)
    executor.shutdown(timeout_sec=0)
    node.destroy_node()
    context.try_shutdown()
    us = sorted(s * 1e6 for s in samples)
    result = {
        "rate_hz": rate,
        "depth": depth,
        "sent": count,
        "received": len(us),
        "p50_us": round(statistics.median(us), 1) if us else None,
        "p99_us": round(us[int(len(us) * 0.99) - 1], 1) if us else None,
        "max_us": round(us[-1], 1) if us else None,
        "rmw": rclpy.get_rmw_implementation_identifier(),
        "discovery_range": os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "(default)"),
    }
    print(json.dumps(result))


def release() -> None:
    """Say which ROS 2 release this interpreter's rclpy comes from (wheels or a sourced ROS)."""
    from importlib import metadata

    dists = metadata.packages_distributions().get("rclpy", [])
    versions = {d: metadata.version(d) for d in dists}
    print(json.dumps({
        "rclpy": versions.get("ros-rclpy") or next(iter(versions.values()), "unknown"),
        "distributions": versions,
        "ros_distro": os.environ.get("ROS_DISTRO"),
        "rmw": rclpy.get_rmw_implementation_identifier(),
        "python": ".".join(map(str, sys.version_info[:3])),
        "path": os.path.dirname(rclpy.__file__),
    }))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", nargs="?", default="serve",
                        choices=["serve", "latency", "latency-pub", "release"])
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--count", type=int, default=5000)
    parser.add_argument("--depth", type=int, default=10, help="QoS KEEP_LAST depth")
    args = parser.parse_args()
    if args.mode == "serve":
        Peer().serve()
    elif args.mode == "release":
        release()
    elif args.mode == "latency":
        latency(args.rate, args.count, args.depth)
    else:
        latency_pub(args.rate, args.count, args.depth)


if __name__ == "__main__":
    main()
