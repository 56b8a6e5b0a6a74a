"""The in-process bus: the embedded default middleware.

A topic table inside the server process with ROS-shaped types (:mod:`.msgtypes`). It exists so
the bridge is useful (and testable) without ROS: clients publish and subscribe to each other
through it, and the CLI's ``topic`` tools work against it.

Delivery is synchronous, in the publisher's thread, in order. The hot path has no per-value
Python work when publisher and subscriber bind the same field: the batch is handed over as is.
Only when they bind different fields of one type is each value rebuilt through a full message.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from mypy_extensions import mypyc_attr

from rlbridge.adapters.base import (
    BindingError,
    GoalDone,
    GoalFeedback,
    GoalHandle,
    QoS,
    ServiceHandler,
    ServiceServer,
    ValuesCallback,
    ValueSpec,
)
from rlbridge.adapters.inproc_services import InProcessServices
from rlbridge.adapters.msgtypes import TypeRegistry, get_path, split_path, with_path

_Convert = Callable[[Sequence[Any]], Sequence[Any]]


def _same(values: Sequence[Any]) -> Sequence[Any]:
    """The converter between equal fields; ``deliver`` recognises it and skips the call."""
    return values


def _converter(spec_from: ValueSpec, spec_to: ValueSpec, template: dict[str, Any]) -> _Convert:
    """How a batch bound to one field reaches a subscriber bound to another field."""
    if spec_from.field == spec_to.field:
        return _same
    src = split_path(spec_from.field) if spec_from.field is not None else None
    dst = split_path(spec_to.field) if spec_to.field is not None else None

    def message(value: Any) -> dict[str, Any]:
        return dict(value) if src is None else with_path(template, src, value)

    if dst is None:
        return lambda values: [message(v) for v in values]
    return lambda values: [get_path(message(v), dst) for v in values]


@dataclass(eq=False)
class _Subscriber:
    spec: ValueSpec
    callback: ValuesCallback
    topic: _Topic
    closed: bool = False
    #: Synchronous delivery loses nothing (the Subscription Protocol's counter).
    lost: int = 0

    def close(self) -> None:
        self.topic.remove_subscriber(self)


@dataclass(eq=False)
class _Publisher:
    spec: ValueSpec
    topic: _Topic
    closed: bool = False
    #: The bus refuses nothing it validated (the Publisher Protocol's counter).
    failed: int = 0
    #: ``transient_local`` publishers keep their last ``depth`` values for late subscribers.
    latched: deque[Any] | None = None

    #: The topic's subscribers when ``_targets`` was computed (a new tuple on every change).
    _seen: tuple[_Subscriber, ...] | None = field(default=None, init=False, repr=False)
    #: Each subscriber with the converter this publisher's values need (None: as they are).
    _targets: tuple[tuple[_Subscriber, _Convert | None], ...] = field(
        default=(), init=False, repr=False)

    def __post_init__(self) -> None:
        # A dataclass compiled by mypyc (setup.py) leaves ``init=False`` fields unset.
        self._seen = None
        self._targets = ()

    def publish(self, values: Sequence[Any]) -> None:
        """``_Topic.deliver`` with this publisher's fan-out computed once per subscriber set."""
        if self.closed:
            raise RuntimeError(f"publisher on {self.topic.name} is closed")
        if self.latched is not None:
            self.latched.extend(values)
        if not values:
            return
        subscribers = self.topic.subscribers
        if subscribers is not self._seen:
            self._targets = self.topic.targets(self.spec)
            self._seen = subscribers
        for sub, convert in self._targets:
            if not sub.closed:  # closed during this delivery (by an earlier subscriber)
                sub.callback(values if convert is None else convert(values))

    def close(self) -> None:
        self.topic.remove_publisher(self)


@dataclass(eq=False)
class _Topic:
    """One topic: its type, its endpoints, and cached field-to-field converters."""

    name: str
    msg_type: str
    template: dict[str, Any]
    bus: InProcessBus
    subscribers: tuple[_Subscriber, ...] = ()
    publishers: int = 0
    latching: list[_Publisher] = field(default_factory=list)
    converters: dict[tuple[str | None, str | None], _Convert] = field(default_factory=dict)

    def targets(self, spec: ValueSpec) -> tuple[tuple[_Subscriber, _Convert | None], ...]:
        """Every subscriber, with what values of ``spec`` need to reach it (None: nothing).

        A tuple over ``subscribers`` (itself replaced, never changed, on subscribe and close),
        so a subscribe or close during a delivery does not disturb it.
        """
        out = []
        for sub in self.subscribers:
            convert = self.converter(spec, sub)
            out.append((sub, None if convert is _same else convert))
        return tuple(out)

    def converter(self, spec: ValueSpec, sub: _Subscriber) -> _Convert:
        """The cached converter from values of ``spec`` to ``sub``'s field."""
        key = (spec.field, sub.spec.field)
        convert = self.converters.get(key)
        if convert is None:
            convert = self.converters[key] = _converter(spec, sub.spec, self.template)
        return convert

    def deliver_to(self, sub: _Subscriber, spec: ValueSpec, values: Sequence[Any]) -> None:
        convert = self.converter(spec, sub)
        sub.callback(values if convert is _same else convert(values))

    def remove_subscriber(self, sub: _Subscriber) -> None:
        with self.bus.lock:
            if sub.closed:
                return
            sub.closed = True
            self.subscribers = tuple(s for s in self.subscribers if s is not sub)
            self.bus.forget_if_unused(self)

    def remove_publisher(self, pub: _Publisher) -> None:
        with self.bus.lock:
            if pub.closed:
                return
            pub.closed = True
            self.publishers -= 1
            if pub in self.latching:  # as in ROS: a latched value lives with its publisher
                self.latching.remove(pub)
            self.bus.forget_if_unused(self)


# Compiled by mypyc (rlbridge/_compiled.py); tests subclass it in Python (failing buses).
@mypyc_attr(allow_interpreted_subclasses=True)
class InProcessBus:
    """A :class:`~rlbridge.adapters.base.MiddlewareAdapter` living in the server process."""

    name = "inproc"

    def __init__(self, registry: TypeRegistry | None = None) -> None:
        self.registry = registry or TypeRegistry()
        self.lock = threading.Lock()
        self._topics: dict[str, _Topic] = {}
        self._closed = False
        #: Services provided by clients (through the server); see :mod:`.inproc_services`.
        self.service_table = InProcessServices()

    def resolve(self, msg_type: str, field: str | None) -> ValueSpec:
        return self.registry.resolve(msg_type, field)

    def _topic(self, topic: str, spec: ValueSpec) -> _Topic:
        """Find or create the topic; the caller holds the lock."""
        if self._closed:
            raise BindingError("INTERNAL", "the in-process bus is closed")
        _check_topic_name(topic)
        existing = self._topics.get(topic)
        if existing is not None:
            if existing.msg_type != spec.msg_type:
                raise BindingError(
                    "TYPE_CLASH",
                    f"topic '{topic}' has type {existing.msg_type}, not {spec.msg_type}",
                )
            return existing
        template = self.registry.resolve(spec.msg_type, None).default
        created = _Topic(topic, spec.msg_type, template, self)
        self._topics[topic] = created
        return created

    def create_publisher(
        self, topic: str, msg_type: str, field: str | None, qos: QoS
    ) -> _Publisher:
        spec = self.resolve(msg_type, field)
        if qos.durability == "match":
            raise BindingError("BAD_VALUE", "durability 'match' is for subscriptions")
        with self.lock:
            t = self._topic(topic, spec)
            t.publishers += 1
            pub = _Publisher(spec, t)
            if qos.durability == "transient_local":
                pub.latched = deque(maxlen=max(1, qos.depth))
                t.latching.append(pub)
        return pub

    def subscribe(
        self, topic: str, msg_type: str, field: str | None, qos: QoS, callback: ValuesCallback
    ) -> _Subscriber:
        spec = self.resolve(msg_type, field)
        with self.lock:
            t = self._topic(topic, spec)
            sub = _Subscriber(spec, callback, t)
            t.subscribers = (*t.subscribers, sub)
            # transient_local (or matching a latched publisher): the values kept so far first
            history = [(p.spec, list(p.latched)) for p in t.latching
                       if p.latched and qos.durability != "volatile"]
        for pub_spec, values in history:
            t.deliver_to(sub, pub_spec, values)
        return sub

    def topics(self) -> list[tuple[str, str]]:
        with self.lock:
            return sorted((t.name, t.msg_type) for t in self._topics.values())

    def call_service(
        self, service: str, srv_type: str, request: dict[str, Any], timeout: float
    ) -> dict[str, Any]:
        return self.service_table.call(service, srv_type, request, timeout)

    def serve_service(
        self, service: str, srv_type: str, handler: ServiceHandler
    ) -> ServiceServer:
        if self._closed:
            raise BindingError("INTERNAL", "the in-process bus is closed")
        return self.service_table.serve(service, srv_type, handler)

    def services(self) -> list[tuple[str, str]]:
        return self.service_table.listing()

    def send_goal(
        self, action: str, action_type: str, goal: dict[str, Any], feedback: GoalFeedback,
        done: GoalDone, timeout: float,
    ) -> GoalHandle:
        raise BindingError("NO_SERVICE", f"no action server for '{action}': the in-process "
                           "bus has no actions (serve with --adapter ros2)")

    def forget_if_unused(self, topic: _Topic) -> None:
        """Drop a topic nobody uses any more (ROS forgets it too); the caller holds the lock."""
        if not topic.subscribers and topic.publishers == 0:
            self._topics.pop(topic.name, None)

    def close(self) -> None:
        with self.lock:
            self._closed = True
            for t in self._topics.values():
                for sub in t.subscribers:
                    sub.closed = True
                t.subscribers = ()
            self._topics.clear()
        self.service_table.clear()


def _check_topic_name(topic: str) -> None:
    """ROS 2 topic name rules, enough to catch typos before they become silent topics."""
    ok = (
        topic.startswith("/")
        and not topic.endswith("/")
        and "//" not in topic
        and all(c.isalnum() or c in "/_~{}" for c in topic)
        and not any(part[:1].isdigit() for part in topic.split("/"))
    )
    if len(topic) > 1 and ok:
        return
    raise BindingError(
        "BAD_TOPIC",
        f"'{topic}' is not a valid topic name: use '/name' with letters, digits, '_' and '/', "
        "no empty or digit-leading parts",
    )
