"""ROS 2 adapter: close() stops the executor thread, whatever that thread is doing meanwhile.

The executor thread rebuilds its wait set after every callback. rclpy's ``Executor.shutdown()``
destroys the executor's guard condition at once, so a thread caught rebuilding waited without
it, forever, and outlived ``close()`` (CI saw ``rlbridge-ros2-rlbridge_contract`` alive tests
later). These tests put ``close()`` exactly there, and next to delivering callbacks and a
waiting service call, and check the thread is gone when ``close()`` returns.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from contract import Collector

from rlbridge.adapters.base import BindingError, QoS
from waiting import wait_until

ros2 = pytest.importorskip(
    "rlbridge.adapters.ros2",
    reason="rclpy is not installed (pip install 'rlbridge-sdk[ros2]')",
    exc_type=ImportError,
)
callback_groups = pytest.importorskip("rclpy.callback_groups")
ros2_actions = pytest.importorskip("rlbridge.adapters.ros2_actions")

pytestmark = [pytest.mark.ros2, pytest.mark.timeout(60)]

TIMEOUT = 10.0
FLOAT64 = "std_msgs/msg/Float64"
NOT_STOPPED = "did not stop"


@pytest.fixture
def make(ros_env: int) -> Iterator[Callable[[str], Any]]:
    made: list[Any] = []

    def make(node_name: str) -> Any:
        adapter = ros2.Ros2Adapter(node_name, domain_id=ros_env)
        made.append(adapter)
        return adapter

    yield make
    for adapter in made:
        adapter.close()


class _Gate(callback_groups.MutuallyExclusiveCallbackGroup):  # type: ignore[misc]
    """Holds the executor thread inside its wait-set rebuild until released.

    The executor asks every entity's callback group ``can_execute`` while it gathers the wait
    set; a ready entity's group is asked again after the wait, so the gate guards a guard
    condition that is never triggered: the only question it gets is the gathering one.
    """

    def __init__(self) -> None:
        super().__init__()
        self.armed = threading.Event()
        self.entered = threading.Event()
        self.release = threading.Event()

    def can_execute(self, entity: Any) -> bool:
        if self.armed.is_set():
            self.armed.clear()
            self.entered.set()
            self.release.wait(3 * TIMEOUT)
        return bool(super().can_execute(entity))


def _wait_until_joining(thread: threading.Thread) -> None:
    """Wait until ``thread`` blocks in ``Thread.join`` (close() waiting for the executor)."""
    join = threading.Thread.join.__code__

    def joining() -> bool:
        frame = sys._current_frames().get(thread.ident or -1)
        while frame is not None:
            if frame.f_code is join:
                return True
            frame = frame.f_back
        return not thread.is_alive()

    wait_until(joining, "close() to get to joining the executor thread", timeout=TIMEOUT,
               interval=0.005)


def test_close_while_the_executor_rebuilds_its_wait_set(
    make: Callable[[str], Any], caplog: pytest.LogCaptureFixture
) -> None:
    adapter = make("rlbridge_close_gate")
    gate = _Gate()
    adapter.node.create_guard_condition(lambda: None, callback_group=gate)
    # A callback (the kick's) arms the gate: the executor rebuilds its wait set right after
    # it, and the gate holds it there, with the kick's trigger already taken.
    kick = adapter.node.create_guard_condition(gate.armed.set)
    kick.trigger()
    assert gate.entered.wait(TIMEOUT), "the executor thread never rebuilt its wait set"
    executor_thread = next(t for t in threading.enumerate()
                           if t.name == "rlbridge-ros2-rlbridge_close_gate")
    closer = threading.Thread(target=adapter.close, name="test-closer")
    with caplog.at_level(logging.WARNING, logger="rlbridge.adapters.ros2"):
        closer.start()
        _wait_until_joining(closer)  # close() has done all it does before waiting
        gate.release.set()
        closer.join(3 * TIMEOUT)
    assert not closer.is_alive()
    assert not executor_thread.is_alive()
    assert NOT_STOPPED not in caplog.text


def test_close_while_callbacks_deliver(
    make: Callable[[str], Any], unique_topic: Callable[[str], str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    sender = make("rlbridge_close_sender")
    topic = unique_topic("flood")
    pub = sender.create_publisher(topic, FLOAT64, "data", QoS(depth=100))
    stop = threading.Event()

    def flood() -> None:
        while not stop.is_set():
            pub.publish([1.0] * 20)
            time.sleep(0.001)

    flooder = threading.Thread(target=flood, name="test-flood")
    flooder.start()
    try:
        for i in range(3):
            name = f"rlbridge_close_flood{i}"
            receiver = make(name)
            sink = Collector()
            receiver.subscribe(topic, FLOAT64, "data", QoS(depth=100), sink)
            assert sink.wait_for_count(100, TIMEOUT), "the flood never arrived"
            with caplog.at_level(logging.WARNING, logger="rlbridge.adapters.ros2"):
                receiver.close()
            assert f"rlbridge-ros2-{name}" not in [t.name for t in threading.enumerate()]
    finally:
        stop.set()
        flooder.join(TIMEOUT)
    assert NOT_STOPPED not in caplog.text


def test_close_while_a_service_call_waits(
    make: Callable[[str], Any], unique_topic: Callable[[str], str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    provider = make("rlbridge_close_provider")
    caller = make("rlbridge_close_caller")
    service = unique_topic("silent")
    asked = threading.Event()
    provider.serve_service(service, "std_srvs/srv/Trigger", lambda request, reply: asked.set())
    outcome: list[BaseException | dict[str, Any]] = []

    def call() -> None:
        try:
            outcome.append(caller.call_service(service, "std_srvs/srv/Trigger", {}, 3 * TIMEOUT))
        except BaseException as exc:
            outcome.append(exc)

    worker = threading.Thread(target=call, name="test-call")
    worker.start()
    assert asked.wait(TIMEOUT), "the request never reached the provider"
    with caplog.at_level(logging.WARNING, logger="rlbridge.adapters.ros2"):
        caller.close()
    assert "rlbridge-ros2-rlbridge_close_caller" not in [t.name for t in threading.enumerate()]
    assert NOT_STOPPED not in caplog.text
    worker.join(TIMEOUT)  # close() ends the waiting call instead of leaving it to time out
    assert not worker.is_alive()
    assert len(outcome) == 1
    assert isinstance(outcome[0], BindingError), outcome
    assert "closed" in str(outcome[0])


FIBONACCI = "test_msgs/action/Fibonacci"


class _HeldGoals:
    """What the test's action server tells: ``asked`` (a goal came), ``running`` (its execute
    callback runs), ``finished`` (that callback returned); ``release`` lets the held one go on.
    """

    def __init__(self) -> None:
        self.asked, self.running = threading.Event(), threading.Event()
        self.finished, self.release = threading.Event(), threading.Event()


def _hold_goals(provider: Any, action: str, hold_accept: bool) -> _HeldGoals:
    """An action server on ``provider``'s node that holds a goal: its accept (then rejects
    it), or its result (then aborts it)."""
    rclpy_action = pytest.importorskip("rclpy.action")
    fibonacci = __import__("test_msgs.action", fromlist=["Fibonacci"]).Fibonacci
    held = _HeldGoals()

    def on_goal(_request: Any) -> Any:
        held.asked.set()
        if hold_accept:
            held.release.wait(3 * TIMEOUT)
            return rclpy_action.GoalResponse.REJECT  # no execute task left behind
        return rclpy_action.GoalResponse.ACCEPT

    def execute(handle: Any) -> Any:
        held.running.set()
        held.release.wait(3 * TIMEOUT)
        handle.abort()
        held.finished.set()
        return fibonacci.Result()

    full = provider.full_topic_name(action)
    rclpy_action.ActionServer(provider.node, fibonacci, full, execute, goal_callback=on_goal,
                              callback_group=callback_groups.ReentrantCallbackGroup())
    return held


def test_close_while_a_goal_waits_for_its_accept(
    make: Callable[[str], Any], unique_topic: Callable[[str], str],
) -> None:
    provider = make("rlbridge_close_action_server")
    caller = make("rlbridge_close_goal_sender")
    action = unique_topic("held_accept")
    held = _hold_goals(provider, action, hold_accept=True)
    outcome: list[BaseException | Any] = []

    def send() -> None:
        try:
            outcome.append(caller.send_goal(action, FIBONACCI, {"order": 3},
                                            lambda _f: None, lambda _s, _r: None, 3 * TIMEOUT))
        except BaseException as exc:
            outcome.append(exc)

    worker = threading.Thread(target=send, name="test-goal")
    worker.start()
    try:
        assert held.asked.wait(TIMEOUT), "the goal never reached the action server"
        caller.close()
        worker.join(TIMEOUT)  # close() ends the wait instead of leaving it to time out
        assert not worker.is_alive()
    finally:
        held.release.set()
    assert len(outcome) == 1
    assert isinstance(outcome[0], BindingError), outcome
    assert "closed" in str(outcome[0])


def test_close_ends_a_goal_waiting_for_its_result(
    make: Callable[[str], Any], unique_topic: Callable[[str], str],
) -> None:
    provider = make("rlbridge_close_action_runner")
    caller = make("rlbridge_close_goal_waiter")
    action = unique_topic("held_result")
    held = _hold_goals(provider, action, hold_accept=False)
    ended: list[tuple[int, dict[str, Any]]] = []
    try:
        caller.send_goal(action, FIBONACCI, {"order": 3}, lambda _f: None,
                         lambda s, r: ended.append((s, r)), TIMEOUT)
        assert held.running.wait(TIMEOUT), "the goal never ran"
        assert ended == []  # accepted; the server holds the result
        caller.close()
        assert ended == [(ros2_actions.STATUS_CLOSED, {})]  # ended by close(), once
    finally:
        held.release.set()
    # The server's execute task ends before the server's adapter closes (left unawaited, its
    # coroutine would be an unraisable warning).
    assert held.finished.wait(TIMEOUT)


def test_an_action_client_is_countable_the_moment_its_node_holds_it(
    make: Callable[[str], Any], unique_topic: Callable[[str], str],
) -> None:
    """rclpy adds a new action client to its node's waitables before it creates the lock
    that counting its entities takes; an executor counting in that window died (CI, 3.13).
    The node here counts every waitable the moment it is added, as such an executor does."""
    adapter = make("rlbridge_client_in_the_window")
    fibonacci = __import__("test_msgs.action", fromlist=["Fibonacci"]).Fibonacci
    node = adapter.node
    add = node.add_waitable
    counted: list[Any] = []

    def add_and_count(waitable: Any) -> None:
        add(waitable)
        counted.append(waitable.get_num_entities())  # what the executor's rebuild does

    node.add_waitable = add_and_count
    try:
        client = ros2_actions.SafeActionClient(node, fibonacci, unique_topic("in_window"))
        assert len(counted) == 1
        client.destroy()
    finally:
        node.add_waitable = add
