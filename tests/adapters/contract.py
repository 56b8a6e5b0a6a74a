"""The adapter conformance suite: what every middleware adapter promises the server.

Modelled on trio's ``check_two_way_stream``: one set of tests, written against the
:class:`~rlbridge.adapters.base.MiddlewareAdapter` Protocol only, that each adapter runs on
itself by subclassing :class:`AdapterContract` and implementing :meth:`make_adapter`::

    class TestMyAdapter(AdapterContract):
        def make_adapter(self) -> MiddlewareAdapter:
            return MyAdapter()

The tests assume nothing about threads: subscriber callbacks may run on the publisher's thread
(the in-process bus) or on another one (ROS 2's executor), so values are collected into a
thread-safe :class:`Collector` and waited for with a bounded wait, never a fixed sleep. A
middleware with discovery (DDS) may drop what is published before publisher and subscription
have matched, so :meth:`AdapterContract.sync` publishes a probe until one arrives, and
assertions look at what arrives after the probes.

Topics are unique per test (:meth:`AdapterContract.topic`), so a middleware whose graph outlives
one adapter (ROS 2) does not carry one test's topic types into the next.
"""

from __future__ import annotations

import itertools
import threading
import uuid
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import msgspec
import pytest

from rlbridge.adapters.base import (
    BindingError,
    MiddlewareAdapter,
    Publisher,
    QoS,
    Subscription,
    ValueSpec,
)
from waiting import wait_until

FLOAT64 = "std_msgs/msg/Float64"
INT8 = "std_msgs/msg/Int8"
INT32 = "std_msgs/msg/Int32"
BOOL = "std_msgs/msg/Bool"
STRING = "std_msgs/msg/String"
TWIST = "geometry_msgs/msg/Twist"
POSE = "geometry_msgs/msg/Pose"

ZERO3 = {"x": 0.0, "y": 0.0, "z": 0.0}
TWIST_DEFAULT = {"linear": ZERO3, "angular": ZERO3}

#: Enough history for every value of a test to be queued at once (KEEP_LAST drops beyond).
DEEP = QoS(depth=1000)


class Collector:
    """A thread-safe ``ValuesCallback``: records every batch, lets a test wait for a condition."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._batches: list[list[Any]] = []
        self.sequence_types: set[bool] = set()

    def __call__(self, values: Sequence[Any]) -> None:
        with self._cond:
            self.sequence_types.add(isinstance(values, Sequence))
            self._batches.append(list(values))
            self._cond.notify_all()

    @property
    def batches(self) -> list[list[Any]]:
        with self._cond:
            return [list(b) for b in self._batches]

    @property
    def values(self) -> list[Any]:
        with self._cond:
            return [v for batch in self._batches for v in batch]

    def wait_values(self, predicate: Callable[[list[Any]], bool], timeout: float) -> bool:
        """Wait (bounded, woken by each batch: no polling) until ``predicate(values)`` holds;
        returns whether it did. (Polling waits: ``waiting.wait_until``.)"""
        with self._cond:
            return self._cond.wait_for(
                lambda: predicate([v for b in self._batches for v in b]), timeout
            )

    def wait_for_count(self, count: int, timeout: float) -> bool:
        return self.wait_values(lambda values: len(values) >= count, timeout)


class AdapterContract:
    """Subclass, implement :meth:`make_adapter`, and pytest runs the whole contract on it."""

    #: Upper bound for any single wait for delivery (seconds); a middleware with discovery may
    #: need most of it the first time, an in-process one needs none of it.
    timeout: float = 10.0

    def make_adapter(self) -> MiddlewareAdapter:
        raise NotImplementedError("an AdapterContract subclass must implement make_adapter()")

    @pytest.fixture
    def adapter(self) -> Iterator[MiddlewareAdapter]:
        adapter = self.make_adapter()
        try:
            yield adapter
        finally:
            adapter.close()

    @pytest.fixture
    def topic(self, request: pytest.FixtureRequest) -> Callable[[str], str]:
        """``topic("x")`` -> a topic name unique to this test run, e.g. ``/rlb_a1b2c3_x``."""
        run = uuid.uuid4().hex[:8]
        return lambda suffix: f"/rlb_{run}_{suffix}"

    # -- helpers

    def sync(
        self, pub: Publisher, sink: Collector, probe: Any, *, interval: float = 0.02
    ) -> None:
        """Publish ``probe`` until the subscriber sees one (bounded by :attr:`timeout`)."""

        def arrived() -> bool:
            pub.publish([probe])
            return sink.wait_for_count(1, interval)

        wait_until(arrived, "a value to arrive (discovery never matched?)",
                   timeout=self.timeout, interval=0.0)

    def expect_after_probes(
        self, sink: Collector, probe: Any, expected: list[Any]
    ) -> list[Any]:
        """Wait until ``expected`` arrived after the probes; return everything received."""

        def done(values: list[Any]) -> bool:
            return len(values) >= len(expected) and values[len(values) - len(expected):] == expected

        if not sink.wait_values(done, self.timeout):
            pytest.fail(f"expected {expected!r} after probes, got {sink.values!r}")
        received = sink.values
        head = received[: len(received) - len(expected)]
        assert all(v == probe for v in head), f"unexpected values before {expected!r}: {head!r}"
        return received

    def round_trip(
        self,
        adapter: MiddlewareAdapter,
        topic: str,
        msg_type: str,
        values: list[Any],
        *,
        pub_field: str | None = "data",
        sub_field: str | None = "data",
        probe: Any,
        seen_probe: Any = None,
        expected: list[Any] | None = None,
    ) -> Collector:
        """Publish ``values`` on one binding, check another binding of the topic receives them.

        ``probe`` syncs discovery first; ``seen_probe`` and ``expected`` are what the subscriber
        sees when it binds another field than the publisher (default: the same values).
        """
        sink = Collector()
        sub = adapter.subscribe(topic, msg_type, sub_field, DEEP, sink)
        pub = adapter.create_publisher(topic, msg_type, pub_field, DEEP)
        self.sync(pub, sink, probe)
        pub.publish(values)
        self.expect_after_probes(
            sink,
            probe if seen_probe is None else seen_probe,
            values if expected is None else expected,
        )
        pub.close()
        sub.close()
        return sink

    # -- resolve

    def test_has_a_name(self, adapter: MiddlewareAdapter) -> None:
        assert isinstance(adapter.name, str)
        assert adapter.name

    @pytest.mark.parametrize(
        ("msg_type", "field", "good", "default"),
        [
            (FLOAT64, "data", 1.5, 0.0),
            (INT32, "data", -(2**31), 0),
            (INT8, "data", 127, 0),
            (BOOL, "data", True, False),
            (STRING, "data", "héllo", ""),
            (TWIST, "linear.x", -2.5, 0.0),
            (POSE, "orientation.w", 0.5, 1.0),
        ],
    )
    def test_resolve_field(
        self, adapter: MiddlewareAdapter, msg_type: str, field: str, good: Any, default: Any
    ) -> None:
        spec = adapter.resolve(msg_type, field)
        assert isinstance(spec, ValueSpec)
        assert spec.msg_type == msg_type
        assert spec.field == field
        assert msgspec.convert(good, spec.python_type) == good
        assert spec.default == default
        assert type(spec.default) is type(default)

    @pytest.mark.parametrize(
        ("msg_type", "field", "bad"),
        [
            (INT8, "data", 128),
            (INT8, "data", -129),
            (INT32, "data", 2**31),
            (INT32, "data", 1.5),
            (FLOAT64, "data", "1.0"),
            (BOOL, "data", 1),
            (STRING, "data", 3),
        ],
    )
    def test_resolved_type_rejects_bad_values(
        self, adapter: MiddlewareAdapter, msg_type: str, field: str, bad: Any
    ) -> None:
        spec = adapter.resolve(msg_type, field)
        with pytest.raises(msgspec.ValidationError):
            msgspec.convert(bad, spec.python_type)

    def test_resolve_whole_message(self, adapter: MiddlewareAdapter) -> None:
        spec = adapter.resolve(TWIST, None)
        assert spec.field is None
        assert spec.default == TWIST_DEFAULT
        assert msgspec.to_builtins(msgspec.convert(spec.default, spec.python_type)) == spec.default
        partial = msgspec.convert({"linear": {"x": 1}}, spec.python_type)
        assert msgspec.to_builtins(partial) == {
            "linear": {"x": 1.0, "y": 0.0, "z": 0.0},
            "angular": ZERO3,
        }
        with pytest.raises(msgspec.ValidationError):
            msgspec.convert({"linear": {"w": 1.0}}, spec.python_type)
        with pytest.raises(msgspec.ValidationError):
            msgspec.convert({"bogus": 1}, spec.python_type)
        pose = adapter.resolve(POSE, None)
        assert pose.default["orientation"] == {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}

    def test_resolve_accepts_ros1_style_names(self, adapter: MiddlewareAdapter) -> None:
        assert adapter.resolve("std_msgs/Float64", "data").msg_type == FLOAT64

    @pytest.mark.parametrize(
        ("msg_type", "field", "code", "mentions"),
        [
            ("std_msgs/msg/NoSuchType", "data", "UNKNOWN_TYPE", ["NoSuchType"]),
            ("Float64", "data", "UNKNOWN_TYPE", ["Float64"]),
            ("std_msgs/msg/Float64/extra", "data", "UNKNOWN_TYPE", []),
            (FLOAT64, "value", "NO_SUCH_FIELD", ["value", "data"]),
            (TWIST, "linear.w", "NO_SUCH_FIELD", ["linear.w", "x", "y", "z"]),
            (TWIST, "sideways", "NO_SUCH_FIELD", ["linear", "angular"]),
            (TWIST, "linear.x.y", "NO_SUCH_FIELD", ["linear.x.y"]),
            (TWIST, "linear..x", "NO_SUCH_FIELD", []),
        ],
    )
    def test_resolve_errors(
        self,
        adapter: MiddlewareAdapter,
        topic: Callable[[str], str],
        msg_type: str,
        field: str,
        code: str,
        mentions: list[str],
    ) -> None:
        for attempt in (
            lambda: adapter.resolve(msg_type, field),
            lambda: adapter.create_publisher(topic("e"), msg_type, field, QoS()),
            lambda: adapter.subscribe(topic("e"), msg_type, field, QoS(), Collector()),
        ):
            with pytest.raises(BindingError) as info:
                attempt()
            assert info.value.code == code
            for word in mentions:
                assert word in info.value.reason

    def test_missing_package_is_an_error(self, adapter: MiddlewareAdapter) -> None:
        with pytest.raises(BindingError) as info:
            adapter.resolve("rlbridge_no_such_msgs/msg/Thing", None)
        assert info.value.code in {"UNKNOWN_TYPE", "PACKAGE_MISSING"}
        assert "rlbridge_no_such_msgs" in info.value.reason

    # -- binding errors

    @pytest.mark.parametrize(
        ("first", "second"),
        [("publisher", "subscription"), ("subscription", "publisher"), ("publisher", "publisher")],
    )
    def test_type_clash(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str], first: str, second: str
    ) -> None:
        name = topic("clash")

        def bind(kind: str, msg_type: str) -> Publisher | Subscription:
            if kind == "publisher":
                return adapter.create_publisher(name, msg_type, "data", QoS())
            return adapter.subscribe(name, msg_type, "data", QoS(), Collector())

        bind(first, FLOAT64)
        with pytest.raises(BindingError) as info:
            bind(second, INT32)
        assert info.value.code == "TYPE_CLASH"
        assert FLOAT64 in info.value.reason
        assert INT32 in info.value.reason
        bind(second, FLOAT64)  # the same type again is fine

    @pytest.mark.parametrize("bad", ["", "/", "no space", "/a//b", "/1abc", "/trailing/", "/a-b"])
    def test_bad_topic_names(self, adapter: MiddlewareAdapter, bad: str) -> None:
        with pytest.raises(BindingError) as info:
            adapter.create_publisher(bad, FLOAT64, "data", QoS())
        assert info.value.code == "BAD_TOPIC"
        with pytest.raises(BindingError) as info:
            adapter.subscribe(bad, FLOAT64, "data", QoS(), Collector())
        assert info.value.code == "BAD_TOPIC"

    # -- delivery

    def test_float_round_trip(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        values = [0.0, -1.5, 3.25, 1e300, -1e-300]
        sink = self.round_trip(adapter, topic("f"), FLOAT64, values, probe=42.0)
        assert all(type(v) is float for v in sink.values)

    def test_int_round_trip_at_the_range_limits(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        self.round_trip(adapter, topic("i8"), INT8, [-128, 127, 0, -1], probe=7)
        sink = self.round_trip(
            adapter, topic("i32"), INT32, [-(2**31), 2**31 - 1, 12345], probe=7
        )
        assert all(type(v) is int for v in sink.values)

    def test_bool_round_trip(self, adapter: MiddlewareAdapter, topic: Callable[[str], str]) -> None:
        sink = self.round_trip(adapter, topic("b"), BOOL, [True, False, True], probe=False)
        assert all(type(v) is bool for v in sink.values)

    def test_str_round_trip(self, adapter: MiddlewareAdapter, topic: Callable[[str], str]) -> None:
        values = ["", "plain", "ünïcødé ✓", "x" * 1000]
        self.round_trip(adapter, topic("s"), STRING, values, probe="probe")

    def test_nested_field_round_trip(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        self.round_trip(
            adapter, topic("tw"), TWIST, [1.0, -2.0], pub_field="linear.x", sub_field="linear.x",
            probe=9.0,
        )

    def test_other_fields_keep_their_defaults(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        """A field-bound publisher sends a fresh message: every other field is its default."""
        self.round_trip(
            adapter, topic("tw2"), TWIST, [1.0, -2.0], pub_field="linear.x",
            sub_field="angular.z", probe=9.0, seen_probe=0.0, expected=[0.0, 0.0],
        )
        self.round_trip(
            adapter, topic("pose"), POSE, [3.0], pub_field="position.x",
            sub_field="orientation.w", probe=9.0, seen_probe=1.0, expected=[1.0],
        )

    def test_field_to_whole_message(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        seen_probe, expected = (
            {"linear": {"x": v, "y": 0.0, "z": 0.0}, "angular": ZERO3} for v in (9.0, 1.0)
        )
        self.round_trip(
            adapter, topic("tw3"), TWIST, [1.0], pub_field="linear.x", sub_field=None,
            probe=9.0, seen_probe=seen_probe, expected=[expected],
        )

    def test_whole_message_round_trip(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        spec = adapter.resolve(TWIST, None)
        values = [
            {"linear": {"x": float(i), "y": -1.0, "z": 0.5}, "angular": {"x": 0.0, "y": 2.0,
             "z": float(-i)}}
            for i in range(5)
        ]
        # What the server hands over: validated, then plain builtins.
        values = [msgspec.to_builtins(msgspec.convert(v, spec.python_type)) for v in values]
        sink = self.round_trip(
            adapter, topic("whole"), TWIST, values, pub_field=None, sub_field=None,
            probe=TWIST_DEFAULT,
        )
        assert all(isinstance(v, dict) for v in sink.values)

    def test_whole_message_to_field(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        whole = {
            "linear": {"x": 1.0, "y": 2.0, "z": 3.0},
            "angular": {"x": 4.0, "y": 5.0, "z": 6.0},
        }
        self.round_trip(
            adapter, topic("w2f"), TWIST, [whole], pub_field=None, sub_field="angular.y",
            probe=TWIST_DEFAULT, seen_probe=0.0, expected=[5.0],
        )

    def test_several_subscribers_get_every_value(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        name = topic("fan")
        sinks = [Collector() for _ in range(3)]
        for sink in sinks[:2]:
            adapter.subscribe(name, TWIST, "linear.x", DEEP, sink)
        adapter.subscribe(name, TWIST, None, DEEP, sinks[2])
        pub = adapter.create_publisher(name, TWIST, "linear.x", DEEP)
        self._sync_all(pub, sinks, -1.0)
        pub.publish([1.0, 2.0, 3.0])
        for sink in sinks[:2]:
            self.expect_after_probes(sink, -1.0, [1.0, 2.0, 3.0])
        whole = [
            {"linear": {"x": v, "y": 0.0, "z": 0.0}, "angular": ZERO3} for v in (1.0, 2.0, 3.0)
        ]
        probe = {"linear": {"x": -1.0, "y": 0.0, "z": 0.0}, "angular": ZERO3}
        self.expect_after_probes(sinks[2], probe, whole)

    def _sync_all(self, pub: Publisher, sinks: list[Collector], probe: Any) -> None:

        def arrived() -> bool:
            pub.publish([probe])
            return all(s.wait_for_count(1, 0.02) for s in sinks)

        wait_until(arrived, "a probe at every subscriber (discovery never matched?)",
                   timeout=self.timeout, interval=0.0)

    def test_batches_keep_their_order(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        values = list(range(1, 301))
        sink = self.round_trip(adapter, topic("order"), INT32, values, probe=0)
        assert sink.sequence_types == {True}
        # Ordered inside every batch and across batches.
        assert [v for v in sink.values if v != 0] == values

    def test_empty_batch_is_a_no_op(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        pub = adapter.create_publisher(topic("empty"), FLOAT64, "data", QoS())
        pub.publish([])
        pub.close()

    def test_interleaved_publishers_on_two_topics(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        a, b = Collector(), Collector()
        adapter.subscribe(topic("ta"), INT32, "data", DEEP, a)
        adapter.subscribe(topic("tb"), STRING, "data", DEEP, b)
        pa = adapter.create_publisher(topic("ta"), INT32, "data", DEEP)
        pb = adapter.create_publisher(topic("tb"), STRING, "data", DEEP)
        self.sync(pa, a, 0)
        self.sync(pb, b, "")
        for i in range(1, 21):
            pa.publish([i])
            pb.publish([str(i)])
        self.expect_after_probes(a, 0, list(range(1, 21)))
        self.expect_after_probes(b, "", [str(i) for i in range(1, 21)])

    # -- closing

    def test_closed_subscription_gets_nothing(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        name = topic("close")
        stays, leaves = Collector(), Collector()
        adapter.subscribe(name, FLOAT64, "data", DEEP, stays)
        gone = adapter.subscribe(name, FLOAT64, "data", DEEP, leaves)
        pub = adapter.create_publisher(name, FLOAT64, "data", DEEP)
        self._sync_all(pub, [stays, leaves], -1.0)
        gone.close()
        gone.close()  # idempotent
        before = len(leaves.values)
        pub.publish([1.0, 2.0])
        self.expect_after_probes(stays, -1.0, [1.0, 2.0])
        assert len(leaves.values) == before

    def test_publisher_close_is_idempotent_and_final(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        pub = adapter.create_publisher(topic("pclose"), FLOAT64, "data", QoS())
        pub.close()
        pub.close()
        with pytest.raises(RuntimeError):
            pub.publish([1.0])

    def test_adapter_close_stops_everything(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        sink = Collector()
        sub = adapter.subscribe(topic("end"), FLOAT64, "data", DEEP, sink)
        pub = adapter.create_publisher(topic("end"), FLOAT64, "data", DEEP)
        self.sync(pub, sink, 1.0)
        adapter.close()
        count = len(sink.values)
        adapter.close()  # idempotent
        sub.close()  # closing an endpoint after its adapter is harmless
        pub.close()
        assert len(sink.values) == count
        with pytest.raises(BindingError):
            adapter.create_publisher(topic("after"), FLOAT64, "data", QoS())

    # -- topics

    def test_topics_lists_what_exists(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        pub = adapter.create_publisher(topic("list_a"), FLOAT64, "data", QoS())
        sub = adapter.subscribe(topic("list_b"), TWIST, None, QoS(), Collector())
        listed = adapter.topics()
        assert listed == sorted(listed)
        assert (topic("list_a"), FLOAT64) in listed
        assert (topic("list_b"), TWIST) in listed
        pub.close()
        sub.close()
        listed = adapter.topics()
        assert (topic("list_a"), FLOAT64) not in listed
        assert (topic("list_b"), TWIST) not in listed

    def test_unused_topic_can_change_type(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        """Once nothing uses a topic, it is forgotten (as ROS forgets it) and may be rebound."""
        name = topic("reuse")
        adapter.create_publisher(name, FLOAT64, "data", QoS()).close()
        adapter.subscribe(name, INT32, "data", QoS(), Collector()).close()
        self.round_trip(adapter, name, STRING, ["again"], probe="p")

    def test_many_bindings_come_and_go(
        self, adapter: MiddlewareAdapter, topic: Callable[[str], str]
    ) -> None:
        """Binding and closing repeatedly leaks nothing the adapter keeps listing."""
        names = [topic(f"churn{i}") for i in range(10)]
        for name, _ in itertools.product(names, range(2)):
            adapter.subscribe(name, FLOAT64, "data", QoS(), Collector()).close()
            adapter.create_publisher(name, FLOAT64, "data", QoS()).close()
        listed = {name for name, _ in adapter.topics()}
        assert not listed & set(names)
