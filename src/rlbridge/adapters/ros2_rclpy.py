"""The one place the ROS 2 adapter imports rclpy: a clear error without it, no warnings with it.

Every ``ros2_*`` module that needs rclpy takes its names from here, so importing any of them
without rclpy fails with the same :class:`ImportError` saying what to install, and the
workaround below runs before rclpy loads its first message type support.
"""

from __future__ import annotations

import importlib
import warnings

from rlbridge.adapters.base import RclpyMissing

try:
    # rosidl_generator_py (imported by rclpy when a message's type support is first loaded)
    # imports lark-parser 0.12, which imports the deprecated ``sre_parse``. Import it once here
    # with exactly that warning silenced, so ``-W error`` (and pytest's filterwarnings=error)
    # does not turn the first create_node() into a crash; the module stays cached afterwards.
    with warnings.catch_warnings():
        warnings.filterwarnings(
            "ignore", message=r"module 'sre_(parse|constants)' is deprecated",
            category=DeprecationWarning,
        )
        importlib.import_module("rosidl_generator_py")  # untyped; only its side effect counts

    from rclpy._rclpy_pybind11 import RCLError
    from rclpy.action.client import ActionClient as RclpyActionClient
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
    from rclpy.context import Context
    from rclpy.exceptions import InvalidHandle, InvalidTopicNameException
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.expand_topic_name import expand_topic_name
    from rclpy.node import Node
    from rclpy.publisher import Publisher as RclpyPublisher
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.service import Service as RclpyService
    from rclpy.subscription import Subscription as RclpySubscription
    from rclpy.validate_full_topic_name import validate_full_topic_name
except ImportError as exc:  # pragma: no cover - exercised only where rclpy is missing
    raise RclpyMissing(exc) from exc

__all__ = [
    "Context", "DurabilityPolicy", "ExternalShutdownException", "HistoryPolicy", "InvalidHandle",
    "InvalidTopicNameException", "MutuallyExclusiveCallbackGroup", "Node", "QoSProfile",
    "RCLError", "RclpyActionClient", "RclpyPublisher",
    "RclpyService", "RclpySubscription", "ReliabilityPolicy", "SingleThreadedExecutor",
    "expand_topic_name", "validate_full_topic_name",
]
