"""ROS 2 adapter behaviour beyond the shared contract: names, parameters, lifetimes, failures."""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import pytest
from contract import Collector

from rlbridge.adapters.base import BindingError, MiddlewareAdapter, QoS

ros2 = pytest.importorskip(
    "rlbridge.adapters.ros2",
    reason="rclpy is not installed (pip install 'rlbridge-sdk[ros2]')",
    exc_type=ImportError,
)

pytestmark = [pytest.mark.ros2, pytest.mark.timeout(60)]

TIMEOUT = 10.0
FLOAT64 = "std_msgs/msg/Float64"
INT8 = "std_msgs/msg/Int8"


def _executor_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("rlbridge-ros2-")]


@pytest.fixture
def make(ros_env: int) -> Iterator[Callable[..., Any]]:
    """Create adapters that are closed after the test, whatever happens."""
    made: list[Any] = []

    def make(node_name: str = "rlbridge_test", namespace: str = "", **kwargs: Any) -> Any:
        adapter = ros2.Ros2Adapter(node_name, namespace, domain_id=ros_env, **kwargs)
        made.append(adapter)
        return adapter

    yield make
    for adapter in made:
        adapter.close()


def _sync(pub: Any, sink: Collector, probe: Any) -> None:
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        pub.publish([probe])
        if sink.wait_for_count(1, 0.02):
            return
    pytest.fail("no probe arrived")


def test_is_a_middleware_adapter(make: Callable[..., Any]) -> None:
    adapter = make()
    assert isinstance(adapter, MiddlewareAdapter)
    assert adapter.name == "ros2"


def test_missing_package_names_the_pip_package(make: Callable[..., Any]) -> None:
    with pytest.raises(BindingError) as info:
        make().resolve("rlbridge_absent_msgs/msg/Thing", None)
    assert info.value.code == "PACKAGE_MISSING"
    assert "rlbridge_absent_msgs" in info.value.reason
    assert "pip install ros-rlbridge-absent-msgs" in info.value.reason


def test_node_name_namespace_and_relative_topics(make: Callable[..., Any]) -> None:
    adapter = make("bridge", "/robot1")
    assert adapter.node.get_fully_qualified_name() == "/robot1/bridge"
    relative = adapter.create_publisher("cmd", FLOAT64, "data", QoS())
    private = adapter.create_publisher("~/status", FLOAT64, "data", QoS())
    absolute = adapter.create_publisher("/global", FLOAT64, "data", QoS())
    assert (relative.topic, private.topic, absolute.topic) == (
        "/robot1/cmd", "/robot1/bridge/status", "/global"
    )
    listed = dict(adapter.topics())
    assert listed["/robot1/cmd"] == FLOAT64
    assert listed["/robot1/bridge/status"] == FLOAT64


def test_graph_topics_are_listed(make: Callable[..., Any]) -> None:
    listed = dict(make().topics())
    assert listed["/rosout"] == "rcl_interfaces/msg/Log"
    assert listed["/parameter_events"] == "rcl_interfaces/msg/ParameterEvent"


def test_parameters_are_declared_read_only(make: Callable[..., Any]) -> None:
    adapter = make(parameters={"use_tcp": True, "use_udp": False, "disable_nagle": True,
                               "frequency": 750})
    node = adapter.node
    assert node.get_parameter("use_tcp").value is True
    assert node.get_parameter("use_udp").value is False
    assert node.get_parameter("frequency").value == 750
    rclpy_parameter = pytest.importorskip("rclpy.parameter")
    result = node.set_parameters([rclpy_parameter.Parameter("use_udp", value=True)])
    assert not result[0].successful
    assert node.get_parameter("use_udp").value is False


def test_failed_construction_leaves_nothing_running(ros_env: int) -> None:
    before = _executor_threads()
    with pytest.raises(TypeError):
        ros2.Ros2Adapter("rlbridge_bad_param", parameters={"x": [1, 2]}, domain_id=ros_env)
    with pytest.raises(Exception, match="node name"):
        ros2.Ros2Adapter("not a node name", domain_id=ros_env)
    assert _executor_threads() == before


def test_close_joins_the_executor_thread_and_is_idempotent(ros_env: int) -> None:
    adapter = ros2.Ros2Adapter("rlbridge_close", domain_id=ros_env)
    assert "rlbridge-ros2-rlbridge_close" in _executor_threads()
    adapter.close()
    assert "rlbridge-ros2-rlbridge_close" not in _executor_threads()
    adapter.close()
    assert adapter.topics() == []


def test_context_manager_closes(ros_env: int) -> None:
    with ros2.Ros2Adapter("rlbridge_with", domain_id=ros_env) as adapter:
        adapter.create_publisher("/rlb_with", FLOAT64, "data", QoS())
    assert "rlbridge-ros2-rlbridge_with" not in _executor_threads()


def test_adapters_coexist_and_talk_across_contexts(
    make: Callable[..., Any], unique_topic: Callable[[str], str]
) -> None:
    """Each adapter has its own context (a DDS participant): no shared global state."""
    first, second = make("rlbridge_one"), make("rlbridge_two")
    sink = Collector()
    second.subscribe(unique_topic("x"), FLOAT64, "data", QoS(depth=100), sink)
    pub = first.create_publisher(unique_topic("x"), FLOAT64, "data", QoS(depth=100))
    _sync(pub, sink, -1.0)
    pub.publish([1.0, 2.0])
    assert sink.wait_until(lambda v: v[-2:] == [1.0, 2.0], TIMEOUT)
    first.close()
    assert second.topics()  # the other adapter is unaffected


def _unchecked(reliability: str, depth: int) -> QoS:
    """A QoS that ``QoS(...)`` itself refuses (its check skipped): the adapter's own check,
    for whatever reaches it without the dataclass, is what is tested."""
    qos = object.__new__(QoS)
    for name, value in (("reliability", reliability), ("depth", depth),
                        ("durability", "volatile")):
        object.__setattr__(qos, name, value)
    return qos


@pytest.mark.parametrize(
    ("qos", "words"),
    [(_unchecked("sometimes", 10), ["sometimes"]), (_unchecked("reliable", 0), ["depth"])],
)
def test_bad_qos(
    make: Callable[..., Any], unique_topic: Callable[[str], str], qos: QoS, words: list[str]
) -> None:
    adapter = make()
    for bind in (
        lambda: adapter.create_publisher(unique_topic("q"), FLOAT64, "data", qos),
        lambda: adapter.subscribe(unique_topic("q"), FLOAT64, "data", qos, Collector()),
    ):
        with pytest.raises(BindingError) as info:
            bind()
        assert info.value.code == "BAD_VALUE"
        assert all(w in info.value.reason for w in words)
    # A failed binding claims nothing: the topic can still take another type.
    adapter.create_publisher(unique_topic("q"), INT8, "data", QoS())


def test_a_bad_value_publishes_nothing_of_its_batch(
    make: Callable[..., Any], unique_topic: Callable[[str], str]
) -> None:
    """ROS would silently wrap 300 into an int8; the adapter refuses the whole batch."""
    adapter = make()
    sink = Collector()
    adapter.subscribe(unique_topic("v"), INT8, "data", QoS(depth=100), sink)
    pub = adapter.create_publisher(unique_topic("v"), INT8, "data", QoS(depth=100))
    _sync(pub, sink, 0)
    for bad in ([1, 300], [1, 2.5], [True], ["1"]):
        with pytest.raises(BindingError) as info:
            pub.publish(bad)
        assert info.value.code == "BAD_VALUE"
        assert INT8 in info.value.reason
    pub.publish([5])
    assert sink.wait_until(lambda v: v[-1:] == [5], TIMEOUT)
    assert set(sink.values) == {0, 5}
    assert pub.published == len(sink.values)


def test_whole_message_values_are_validated(
    make: Callable[..., Any], unique_topic: Callable[[str], str]
) -> None:
    pub = make().create_publisher(unique_topic("w"), "geometry_msgs/msg/Twist", None, QoS())
    with pytest.raises(BindingError) as info:
        pub.publish([{"linear": {"x": "fast"}}])
    assert info.value.code == "BAD_VALUE"
    with pytest.raises(BindingError):
        pub.publish([{"linear": {"w": 1.0}}])
    pub.publish([{"linear": {"x": 1}}])  # partial dicts get defaults; ints widen to float


def test_a_burst_arrives_in_order_in_few_batches(
    make: Callable[..., Any], unique_topic: Callable[[str], str]
) -> None:
    """The subscription drains its queue per wake-up: one callback per burst, not per message."""
    adapter = make()
    sink = Collector()
    sub = adapter.subscribe(unique_topic("b"), INT8, "data", QoS(depth=1000), sink)
    pub = adapter.create_publisher(unique_topic("b"), INT8, "data", QoS(depth=1000))
    _sync(pub, sink, 0)
    values = [i % 100 + 1 for i in range(600)]
    pub.publish(values)
    assert sink.wait_until(lambda v: len(v) >= 1 + len(values), TIMEOUT)
    assert sink.values[1:] == values
    assert len(sink.batches) - 1 < len(values) // 2, f"{len(sink.batches)} batches"
    assert (sub.delivered, sub.batches, sub.errors) == (len(sink.values), len(sink.batches), 0)


def test_a_raising_callback_does_not_stop_delivery(
    make: Callable[..., Any], unique_topic: Callable[[str], str], caplog: pytest.LogCaptureFixture
) -> None:
    adapter = make()
    good = Collector()
    calls: list[int] = []

    def bad(values: Sequence[Any]) -> None:
        calls.append(len(values))
        raise RuntimeError("subscriber bug")

    failing = adapter.subscribe(unique_topic("r"), FLOAT64, "data", QoS(depth=100), bad)
    adapter.subscribe(unique_topic("r"), FLOAT64, "data", QoS(depth=100), good)
    pub = adapter.create_publisher(unique_topic("r"), FLOAT64, "data", QoS(depth=100))
    with caplog.at_level(logging.ERROR, logger="rlbridge.adapters.ros2"):
        _sync(pub, good, -1.0)
        for v in (1.0, 2.0, 3.0):
            pub.publish([v])
            assert good.wait_until(lambda got, v=v: got[-1:] == [v], TIMEOUT)
    deadline = time.monotonic() + TIMEOUT
    while failing.lost < len(good.values) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert failing.errors == len(calls) >= 2  # it kept being called after failing
    assert failing.lost == sum(calls) == len(good.values)  # taken, not handed on: lost
    assert "subscriber bug" in caplog.text
    assert _executor_threads()


def test_close_from_inside_a_callback(
    make: Callable[..., Any], unique_topic: Callable[[str], str]
) -> None:
    """A callback may close its own subscription, or the whole adapter, without deadlock."""
    adapter = make()
    closed = threading.Event()
    holder: dict[str, Any] = {}

    def close_self(values: Sequence[Any]) -> None:
        holder["sub"].close()
        closed.set()

    holder["sub"] = adapter.subscribe(unique_topic("c"), FLOAT64, "data", QoS(), close_self)
    pub = adapter.create_publisher(unique_topic("c"), FLOAT64, "data", QoS())
    deadline = time.monotonic() + TIMEOUT
    while not closed.is_set() and time.monotonic() < deadline:
        pub.publish([1.0])
        closed.wait(0.02)
    assert closed.is_set()
    assert holder["sub"].batches == 1

    done = threading.Event()

    def close_adapter(values: Sequence[Any]) -> None:
        adapter.close()
        done.set()

    adapter.subscribe(unique_topic("c2"), FLOAT64, "data", QoS(), close_adapter)
    pub2 = adapter.create_publisher(unique_topic("c2"), FLOAT64, "data", QoS())
    while not done.is_set() and time.monotonic() < deadline + TIMEOUT:
        # The callback's close() stops pub2 a moment before it sets ``done``.
        with contextlib.suppress(RuntimeError):
            pub2.publish([1.0])
        done.wait(0.02)
    assert done.is_set()
    deadline = time.monotonic() + TIMEOUT
    while _executor_threads() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not _executor_threads()


def test_adapters_come_and_go_without_leaking(ros_env: int) -> None:
    def fds() -> int:
        return len(os.listdir("/proc/self/fd"))

    ros2.Ros2Adapter("rlbridge_warm", domain_id=ros_env).close()
    before_fds, before_threads = fds(), threading.active_count()
    for i in range(8):
        with ros2.Ros2Adapter(f"rlbridge_churn{i}", domain_id=ros_env) as adapter:
            adapter.subscribe("/rlb_churn", FLOAT64, "data", QoS(), Collector())
            adapter.create_publisher("/rlb_churn", FLOAT64, "data", QoS()).publish([1.0])
    assert fds() <= before_fds + 2
    assert threading.active_count() == before_threads


def test_rebinding_right_after_close_sees_no_stale_type(
    make: Callable[..., Any], unique_topic: Callable[[str], str]
) -> None:
    """rclpy destroys a closed endpoint only when the executor next wakes; the graph still
    shows it for a moment. That must not turn into a false TYPE_CLASH or a stale topics()."""
    adapter = make()
    for i in range(30):
        name = unique_topic(f"rebind{i}")
        adapter.create_publisher(name, FLOAT64, "data", QoS()).close()
        adapter.subscribe(name, INT8, "data", QoS(), Collector()).close()
        adapter.create_publisher(name, "std_msgs/msg/String", "data", QoS()).close()
        assert name not in dict(adapter.topics())


class _OnePublisherOrMore:
    """The rclpy subscription as :meth:`Ros2Subscription._anonymous` sees it."""

    def __init__(self) -> None:
        self.count = 1

    def get_publisher_count(self) -> int:
        return self.count


def test_sequence_gaps_without_publisher_ids_count_while_one_publisher() -> None:
    """rclpy < 8 (Jazzy) gives sequence numbers but no publisher id: they are one publisher's
    while the subscription has one, and are not compared across publishers."""
    from types import SimpleNamespace

    from rlbridge.adapters.ros2_endpoints import Ros2Subscription

    codec = SimpleNamespace(spec=None, msg_cls=object, decode=lambda m: m)
    got: list[Any] = []
    sub = Ros2Subscription(None, "/t", codec, got.extend)  # type: ignore[arg-type]
    ros = _OnePublisherOrMore()
    sub.ros = ros  # type: ignore[assignment]
    sub._drain = lambda taken: None  # type: ignore[method-assign]

    def message(seq: int, gid: bytes | None = None) -> None:
        info: dict[str, Any] = {"publication_sequence_number": seq}
        if gid is not None:
            info["publisher_gid"] = {"data": gid}
        sub.on_message(seq, info)

    for seq in (5, 6, 9, 10):  # one publisher: 7 and 8 lost
        message(seq)
    assert sub.lost == 2
    ros.count = 2  # a second one: its numbers cannot be told apart, nothing is counted
    for seq in (1, 11, 2, 14):
        message(seq)
    assert sub.lost == 2
    ros.count = 1  # one again: counting starts afresh at its next message
    for seq in (3, 4, 6):
        message(seq)
    assert sub.lost == 3
    for seq in (1, 3):  # with ids (rclpy >= 8), per publisher whatever their number
        message(seq, b"a")
        message(seq + 100, b"b")
    assert sub.lost == 5
    assert len(got) == 4 + 4 + 3 + 4
