"""Middleware adapters behind one small Protocol (:mod:`rlbridge.adapters.base`).

``load_adapter`` is the only place that maps a name to an implementation; the ROS 2 adapter is
imported lazily there, so ``import rlbridge`` never imports rclpy.
"""

from __future__ import annotations

from collections.abc import Mapping

from rlbridge.adapters.base import (
    BindingError,
    MiddlewareAdapter,
    Publisher,
    QoS,
    RclpyMissing,
    Subscription,
    ValueSpec,
)
from rlbridge.adapters.inproc import InProcessBus

ADAPTERS = ("inproc", "ros2")


class AdapterUnavailable(RuntimeError):
    """The chosen middleware cannot be used on this machine; the message says what to install."""


def load_adapter(
    name: str,
    *,
    node_name: str = "rlbridge",
    namespace: str = "",
    parameters: Mapping[str, bool | int | float | str] | None = None,
) -> MiddlewareAdapter:
    """Create the adapter called ``name`` (``inproc`` or ``ros2``)."""
    if name == "inproc":
        return InProcessBus()
    if name == "ros2":
        try:
            from rlbridge.adapters.ros2 import Ros2Adapter
        except RclpyMissing as exc:
            raise AdapterUnavailable(str(exc)) from None
        except ImportError as exc:
            raise AdapterUnavailable(str(RclpyMissing(exc))) from None
        return Ros2Adapter(node_name, namespace, parameters=dict(parameters or {}))
    raise AdapterUnavailable(f"unknown adapter '{name}'; choose one of: {', '.join(ADAPTERS)}")


__all__ = [
    "ADAPTERS", "AdapterUnavailable", "BindingError", "InProcessBus", "MiddlewareAdapter",
    "Publisher", "QoS", "RclpyMissing", "Subscription", "ValueSpec", "load_adapter",
]
