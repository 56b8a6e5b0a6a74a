"""ROS 2 action goals through the adapter's node, as an action client.

:meth:`Ros2Actions.send_goal` runs on a server worker thread: it waits for the action server
(discovery), sends the goal and waits until it is accepted or rejected. Feedback and the
result come later on the executor thread, through the callbacks the server gave; one rclpy
``ActionClient`` per (action, type) is kept, as for service clients.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from rlbridge.adapters.base import BindingError, GoalDone, GoalFeedback
from rlbridge.adapters.ros2_rclpy import RclpyActionClient
from rlbridge.adapters.ros2_services import ServiceOwner, half, interface_class


class _Goal:
    """An accepted goal: what ``cancel`` needs."""

    def __init__(self, handle: Any) -> None:
        self._handle = handle

    def cancel(self) -> None:
        self._handle.cancel_goal_async()


class Ros2Actions:
    """The adapter's action clients (the adapter's lock guards the table)."""

    def __init__(self, adapter: ServiceOwner) -> None:
        self._adapter = adapter
        self._clients: dict[tuple[str, str], Any] = {}

    def send_goal(self, action: str, action_type: str, goal: dict[str, Any],
                  feedback: GoalFeedback, done: GoalDone, timeout: float) -> _Goal:
        adapter = self._adapter
        name, cls = interface_class(action_type, "action")
        catalog = adapter.catalog
        message = half(catalog, f"{name}_Goal", cls.Goal).encode(goal)
        on_feedback = half(catalog, f"{name}_Feedback", cls.Feedback).decode
        on_result = half(catalog, f"{name}_Result", cls.Result).decode
        full = adapter.full_topic_name(action)
        with adapter.lock:
            adapter.check_open()
            client = self._clients.get((full, name))
            if client is None:
                client = self._clients[(full, name)] = RclpyActionClient(adapter.node, cls, full)
        end = time.monotonic() + timeout
        if not client.wait_for_server(timeout_sec=timeout):
            raise BindingError("NO_SERVICE", f"no action server for '{full}' ({name}) "
                               f"within {timeout:g} s")
        accepted = threading.Event()
        future = client.send_goal_async(
            message, feedback_callback=lambda m: feedback(on_feedback(m.feedback)))
        future.add_done_callback(lambda _f: accepted.set())
        if not accepted.wait(max(0.0, end - time.monotonic())):
            raise BindingError("TIMEOUT", f"action server '{full}' did not accept or reject "
                               f"the goal within {timeout:g} s")
        handle = future.result()
        if handle is None or not handle.accepted:
            raise BindingError("GOAL_REJECTED", f"action server '{full}' rejected the goal")

        def finished(f: Any) -> None:
            answer = f.result()
            done(int(answer.status), on_result(answer.result))

        handle.get_result_async().add_done_callback(finished)
        return _Goal(handle)

    def clear(self) -> None:
        self._clients.clear()
