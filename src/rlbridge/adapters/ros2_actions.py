"""ROS 2 action goals through the adapter's node, as an action client.

:meth:`Ros2Actions.send_goal` runs on a server worker thread: it waits for the action server
(discovery), sends the goal and waits until it is accepted or rejected. Feedback and the
result come later on the executor thread, through the callbacks the server gave; one rclpy
``ActionClient`` per (action, type) is kept, as for service clients.

Closing the adapter ends what still waits, at once: a ``send_goal`` waiting for the server or
for the accept gets the closed adapter's ``BindingError``, and an accepted goal whose result
has not come gets ``done(STATUS_CLOSED, {})`` (its result can no longer arrive).
"""

from __future__ import annotations

import threading
import time
from typing import Any

from rlbridge.adapters.base import BindingError, GoalDone, GoalFeedback
from rlbridge.adapters.ros2_rclpy import InvalidHandle, RCLError, RclpyActionClient
from rlbridge.adapters.ros2_services import ServiceOwner, half, interface_class

#: ``GoalStatus.STATUS_UNKNOWN``: the status ``done`` gets when the adapter closed first.
STATUS_CLOSED = 0



class SafeActionClient(RclpyActionClient):  # type: ignore[type-arg]  # generic only on newer rclpy
    """rclpy's ``ActionClient``, safe to create while the adapter's executor thread spins.

    rclpy adds a new client to its node's waitables before it creates the lock that the
    client's ``get_num_entities`` takes: an executor rebuilding its wait set in that window
    raises ``AttributeError`` and its thread dies (seen in CI, rclpy on Python 3.13). The lock
    exists here before rclpy's constructor runs; rclpy then replaces it before anything but
    the executor's count can use the client.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._lock = threading.Lock()
        super().__init__(*args, **kwargs)

class _Ending:
    """Calls a goal's ``done`` once: with its result, or with ``STATUS_CLOSED`` on close."""

    def __init__(self, done: GoalDone) -> None:
        self._done = done
        self._lock = threading.Lock()
        self._ended = False

    def end(self, status: int, result: dict[str, Any]) -> None:
        with self._lock:
            if self._ended:
                return
            self._ended = True
        self._done(status, result)


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
        #: What waiting ``send_goal`` calls wait on; clear() (the adapter closing) sets them.
        self._waiting: set[threading.Event] = set()
        #: Accepted goals whose result has not come; clear() ends them.
        self._running: set[_Ending] = set()

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
                client = self._clients[(full, name)] = SafeActionClient(adapter.node, cls, full)
        accepted = threading.Event()
        ending = _Ending(done)
        with adapter.lock:
            adapter.check_open()
            self._waiting.add(accepted)
        end = time.monotonic() + timeout
        try:
            handle = self._accepted(client, message, accepted, end, full, timeout,
                                    lambda m: feedback(on_feedback(m.feedback)))
            with adapter.lock:
                adapter.check_open()
                self._running.add(ending)
        except (InvalidHandle, RCLError):  # the client was destroyed with the closed adapter
            self._check_open()
            raise
        finally:
            with adapter.lock:
                self._waiting.discard(accepted)

        def finished(f: Any) -> None:
            with adapter.lock:
                self._running.discard(ending)
            answer = f.result()
            ending.end(int(answer.status), on_result(answer.result))

        handle.get_result_async().add_done_callback(finished)
        return _Goal(handle)

    def _accepted(self, client: Any, message: Any, accepted: threading.Event, end: float,
                  full: str, timeout: float, on_feedback: Any) -> Any:
        """Wait for the server and the accept (or the adapter closing); the goal's handle."""
        if not client.wait_for_server(timeout_sec=timeout):
            self._check_open()
            raise BindingError("NO_SERVICE", f"no action server for '{full}' "
                               f"within {timeout:g} s")
        self._check_open()  # closed while it waited for the server
        future = client.send_goal_async(message, feedback_callback=on_feedback)
        future.add_done_callback(lambda _f: accepted.set())
        if not accepted.wait(max(0.0, end - time.monotonic())):
            raise BindingError("TIMEOUT", f"action server '{full}' did not accept or reject "
                               f"the goal within {timeout:g} s")
        if not future.done():  # woken by close()
            self._check_open()
        handle = future.result()
        if handle is None or not handle.accepted:
            raise BindingError("GOAL_REJECTED", f"action server '{full}' rejected the goal")
        return handle

    def _check_open(self) -> None:
        with self._adapter.lock:
            self._adapter.check_open()

    def clear(self) -> None:
        """The adapter is closing (under its lock): forget clients, wake waiting goals."""
        self._clients.clear()
        for accepted in self._waiting:
            accepted.set()

    def end_running(self) -> None:
        """The adapter has closed (not under its lock): end goals whose result never came."""
        with self._adapter.lock:
            running, self._running = list(self._running), set()
        for ending in running:
            ending.end(STATUS_CLOSED, {})
