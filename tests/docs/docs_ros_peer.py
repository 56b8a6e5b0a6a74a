#!/usr/bin/env python3
"""The ROS 2 graph the docs' examples talk to: a plain rclpy node in a process of its own.

Imports nothing from rlbridge. Node ``controller`` with parameter ``kp`` (2.0); service
``/arm/enable`` (std_srvs/SetBool: success = data, message "enabled" or "disabled"); action
``/fibonacci`` (test_msgs/Fibonacci: one feedback message per step); a latched (transient-local,
reliable) ``/map`` std_msgs/String published once, at start. Prints ``ready`` when all is up;
runs until stdin closes. Discovery scope comes from the environment the runner sets.
"""

from __future__ import annotations

import contextlib
import importlib
import sys
import threading
import time
import warnings

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    importlib.import_module("rosidl_generator_py")

import rclpy
from rclpy.action import ActionServer
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import SetBool
from test_msgs.action import Fibonacci

STEP_S = 0.02


def enable(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
    response.success = request.data
    response.message = "enabled" if request.data else "disabled"
    return response


def fibonacci(handle: object) -> Fibonacci.Result:
    order = handle.request.order  # type: ignore[attr-defined]
    sequence = [0, 1]
    for _ in range(1, order):
        sequence.append(sequence[-1] + sequence[-2])
        handle.publish_feedback(Fibonacci.Feedback(sequence=sequence))  # type: ignore[attr-defined]
        time.sleep(STEP_S)
    handle.succeed()  # type: ignore[attr-defined]
    return Fibonacci.Result(sequence=sequence)


def main() -> None:
    rclpy.init(args=[])
    node = Node("controller")
    group = ReentrantCallbackGroup()
    node.create_service(SetBool, "/arm/enable", enable, callback_group=group)
    ActionServer(node, Fibonacci, "/fibonacci", fibonacci, callback_group=group)
    node.declare_parameter("kp", 2.0)
    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         reliability=ReliabilityPolicy.RELIABLE)
    node.create_publisher(String, "/map", latched).publish(String(data="map v1"))
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)
    stop = threading.Event()

    def spin() -> None:
        with contextlib.suppress(ExternalShutdownException):
            while not stop.is_set():
                executor.spin_once(timeout_sec=0.1)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    print("ready", flush=True)
    sys.stdin.read()  # until the runner closes our stdin
    stop.set()
    spinner.join(5.0)
    executor.shutdown(timeout_sec=0)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
