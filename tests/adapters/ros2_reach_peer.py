#!/usr/bin/env python3
"""A plain rclpy node for the services/actions/parameters/latched-topic tests.

Imports nothing from rlbridge. Modes:

``serve``
    Node ``reach_peer``: services ``/reach/set_bool`` (std_srvs/SetBool: success = data,
    message "set to <data>") and ``/reach/basic`` (test_msgs/BasicTypes: the request echoed,
    ``string_value`` reversed), action ``/reach/fibonacci`` (test_msgs/Fibonacci: one feedback
    message per step, ``STEP_S`` apart, cancellable), parameters ``gain`` (1.5), ``mode``
    ("auto"), ``enabled`` (true), and a transient-local (latched) ``/reach/map``
    std_msgs/String published once, at start. Prints ``ready`` when all is up; runs until
    stdin closes.
``flood TOPIC N``
    Publish std_msgs/Int64 probes ``-1, -2, ...`` every 50 ms until a line arrives on stdin,
    then ``0 .. N-1`` as fast as rclpy goes (reliable, depth 1000), each exactly once (a
    publish rmw refuses is made again); print ``probes P refused R``.
``count TOPIC DEPTH [LAST]``
    Subscribe to std_msgs/Int64 with a reliable KEEP_LAST(DEPTH) queue and a slow callback
    (1 ms a message); count messages and the gaps in their publication sequence numbers (from
    the first message on, printed as ``first DATA``); print ``{"received": R, "gaps": G,
    "last": L}`` once message LAST arrived (else after 2 s of quiet).
``latched TOPIC``
    A late subscriber: subscribe to std_msgs/String with a transient-local, reliable
    KEEP_LAST(1) queue, print ``got DATA`` for the first message and exit (after 60 s
    without one: ``nothing``, exit 1).
``call SERVICE``
    Call std_srvs/SetBool ``SERVICE`` (provided by an rlbridge client) with data=true, print
    the response as JSON, exit. Its steps go to stderr; still running after 60 s, it prints
    every thread's stack and exits 1.
"""

from __future__ import annotations

import faulthandler
import importlib
import json
import sys
import threading
import time
import warnings

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    importlib.import_module("rosidl_generator_py")

import contextlib

import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.action import ActionServer, CancelResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Int64, String
from std_srvs.srv import SetBool
from test_msgs.action import Fibonacci
from test_msgs.srv import BasicTypes

STEP_S = 0.05


def serve() -> None:
    rclpy.init(args=[])
    node = Node("reach_peer")
    group = ReentrantCallbackGroup()

    def set_bool(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        response.success = request.data
        response.message = f"set to {request.data}"
        return response

    def basic(request: BasicTypes.Request, response: BasicTypes.Response) -> BasicTypes.Response:
        for name in request.get_fields_and_field_types():
            setattr(response, name, getattr(request, name))
        response.string_value = request.string_value[::-1]
        return response

    def fibonacci(handle: object) -> Fibonacci.Result:
        goal = handle.request  # type: ignore[attr-defined]
        sequence = [0, 1]
        feedback = Fibonacci.Feedback()
        for _ in range(1, goal.order):
            if handle.is_cancel_requested:  # type: ignore[attr-defined]
                handle.canceled()  # type: ignore[attr-defined]
                return Fibonacci.Result(sequence=sequence)
            sequence.append(sequence[-1] + sequence[-2])
            feedback.sequence = sequence
            handle.publish_feedback(feedback)  # type: ignore[attr-defined]
            time.sleep(STEP_S)
        handle.succeed()  # type: ignore[attr-defined]
        return Fibonacci.Result(sequence=sequence)

    node.create_service(SetBool, "/reach/set_bool", set_bool, callback_group=group)
    node.create_service(BasicTypes, "/reach/basic", basic, callback_group=group)
    ActionServer(node, Fibonacci, "/reach/fibonacci", fibonacci, callback_group=group,
                 cancel_callback=lambda _h: CancelResponse.ACCEPT)
    node.declare_parameter("gain", 1.5)
    node.declare_parameter("mode", "auto")
    node.declare_parameter("enabled", True)
    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         reliability=ReliabilityPolicy.RELIABLE)
    node.create_publisher(String, "/reach/map", latched).publish(String(data="map v1"))
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)
    stop = threading.Event()
    spinner = threading.Thread(target=_spin, args=(executor, stop), daemon=True)
    spinner.start()
    print("ready", flush=True)
    sys.stdin.read()  # until the test closes our stdin
    stop.set()
    spinner.join(5.0)
    executor.shutdown(timeout_sec=0)
    node.destroy_node()
    rclpy.try_shutdown()


def _spin(executor: MultiThreadedExecutor, stop: threading.Event) -> None:
    """Until ``stop``, then the caller joins and shuts down: ``executor.shutdown()`` under a
    running spin() can leave the thread waiting forever (see the adapter's close())."""
    with contextlib.suppress(ExternalShutdownException):
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)


def call(service: str) -> None:
    # Where it is, for a test that waits too long: each step on stderr, and every thread's
    # stack (then exit 1) if it is still here after CALL_STACKS_S.
    faulthandler.dump_traceback_later(CALL_STACKS_S, exit=True)
    _step("init")
    rclpy.init(args=[])
    node = Node("reach_caller")
    client = node.create_client(SetBool, service)
    _step("waiting for the service")
    if not client.wait_for_service(timeout_sec=20.0):
        print(json.dumps({"error": "no service"}), flush=True)
        sys.exit(1)
    _step("calling")
    future = client.call_async(SetBool.Request(data=True))
    rclpy.spin_until_future_complete(node, future, timeout_sec=20.0)
    result = future.result()
    print(json.dumps({"success": result.success, "message": result.message}
                     if result is not None else {"error": "no answer"}), flush=True)
    _step("shutting down")
    node.destroy_node()
    rclpy.try_shutdown()
    _step("done")


CALL_STACKS_S = 60.0  # the test waits 90 s


def _step(what: str) -> None:
    print(f"caller {time.monotonic():.3f}: {what}", file=sys.stderr, flush=True)


def flood(topic: str, count: int) -> None:
    rclpy.init(args=[])
    node = Node("reach_flood")
    pub = node.create_publisher(Int64, topic, QoSProfile(depth=1000))
    go = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.readline(), go.set()), daemon=True).start()
    probes = 0
    while not go.wait(0.05):
        probes += 1
        pub.publish(Int64(data=-probes))
    refused = 0
    for i in range(count):
        while True:  # every value is published once, so the sequence numbers stay contiguous
            try:
                pub.publish(Int64(data=i))
                break
            except RCLError:  # Fast DDS: the history is full of unacknowledged samples and
                refused += 1  # the reader did not acknowledge within max_blocking_time
    print(f"probes {probes} refused {refused}", flush=True)
    sys.stdin.read()
    node.destroy_node()
    rclpy.try_shutdown()


def latched(topic: str) -> None:
    rclpy.init(args=[])
    node = Node("reach_late")
    got: list[str] = []
    latched_qos = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(String, topic, lambda msg: got.append(msg.data), latched_qos)
    deadline = time.monotonic() + 60.0
    while not got and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    print(f"got {got[0]}" if got else "nothing", flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    sys.exit(0 if got else 1)


def count_gaps(topic: str, depth: int, last: int | None = None) -> None:
    rclpy.init(args=[])
    node = Node("reach_count")
    state = {"received": 0, "gaps": 0, "last": None, "seq": None, "at": time.monotonic()}

    def on_message(msg: Int64, info: object) -> None:
        seq = info["publication_sequence_number"]  # type: ignore[index]
        if state["seq"] is None:
            print(f"first {msg.data}", flush=True)
        if state["seq"] is not None and seq > state["seq"] + 1:
            state["gaps"] += seq - state["seq"] - 1
        state["seq"] = seq
        state["received"] += 1
        state["last"] = msg.data
        state["at"] = time.monotonic()
        time.sleep(0.001)

    node.create_subscription(Int64, topic, on_message, QoSProfile(depth=depth))
    print("ready", flush=True)
    executor = MultiThreadedExecutor(num_threads=1)
    executor.add_node(node)
    quiet = 2.0 if last is None else 60.0  # with ``last``: until it arrives (it always does:
    # a KEEP_LAST queue keeps the newest messages), the quiet period only a safety net
    while (state["received"] == 0 or time.monotonic() - state["at"] < quiet) and (
            last is None or state["last"] != last):
        executor.spin_once(timeout_sec=0.1)
    print(json.dumps({k: state[k] for k in ("received", "gaps", "last")}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    if sys.argv[1:2] == ["call"]:
        call(sys.argv[2])
    elif sys.argv[1:2] == ["flood"]:
        flood(sys.argv[2], int(sys.argv[3]))
    elif sys.argv[1:2] == ["latched"]:
        latched(sys.argv[2])
    elif sys.argv[1:2] == ["count"]:
        count_gaps(sys.argv[2], int(sys.argv[3]),
                   int(sys.argv[4]) if len(sys.argv) > 4 else None)
    else:
        serve()
