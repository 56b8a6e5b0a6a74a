"""The ROS 2 adapter: client channels bound at run time to rclpy publishers and subscriptions.

Theory of operation
-------------------
One adapter owns one ``rclpy.Context`` (never the global default context, so several adapters,
or a test and an adapter, coexist in one process), one node, and one executor spun in a thread
the adapter starts in its constructor and joins in :meth:`Ros2Adapter.close`: the ROS 2
counterpart of the thesis's asynchronous spinner (section 4.1.1), which replaced ROS 1's
``spinOnce()`` polling loop.

* ``publish`` runs on the caller's thread (the server's event loop). It encodes the whole batch
  first (a bad value publishes nothing), then hands each message to rmw, which copies it into
  the DDS writer's history and returns; rclpy's ``Publisher.publish`` is thread-safe. With
  ``KEEP_LAST`` history a slow or stalled reader never blocks the writer: old samples are
  overwritten (see ``docs/ros2.md`` for measurements).
* Subscription callbacks run on the executor thread. Each callback drains what else is already
  queued on that subscription (``take_message`` until empty, bounded), so a burst costs one
  executor wake-up and one adapter callback with a batch, in order, instead of one per message
  (the thesis's "decode a complete packet at the moment it arrives", for the other direction).
  The server hops to its event loop itself.
* Message types are resolved from their names at run time (:mod:`.ros2_types`), which is what
  ROS 1's ShapeShifter did for the old bridge.

Importing this module imports rclpy: ``rlbridge.adapters.load_adapter`` imports it lazily, and
without rclpy the import fails with an ``ImportError`` that says what to install.
"""

from __future__ import annotations

import importlib
import logging
import threading
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

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
    from rclpy.context import Context
    from rclpy.exceptions import InvalidHandle, InvalidTopicNameException
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.expand_topic_name import expand_topic_name
    from rclpy.node import Node
    from rclpy.publisher import Publisher as RclpyPublisher
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.subscription import Subscription as RclpySubscription
    from rclpy.validate_full_topic_name import validate_full_topic_name
except ImportError as exc:  # pragma: no cover - exercised only where rclpy is missing
    raise ImportError(
        f"the ros2 adapter needs rclpy ({exc}); install rclpy with: pip install 'rlbridge[ros2]'"
    ) from exc

from rlbridge.adapters.base import BindingError, QoS, ValuesCallback, ValueSpec
from rlbridge.adapters.ros2_types import ChannelCodec, MessageCatalog

log = logging.getLogger(__name__)

ParameterValue = bool | int | float | str

#: How many already-queued messages one subscription callback takes along in its batch. Bounds
#: the time one busy topic holds the executor thread, so other subscriptions still get a turn.
MAX_BATCH = 1000

#: How long :meth:`Ros2Adapter.close` waits for the executor thread to stop.
JOIN_TIMEOUT_S = 5.0

_RELIABILITY: Mapping[str, ReliabilityPolicy] = {
    "reliable": ReliabilityPolicy.RELIABLE,
    "best_effort": ReliabilityPolicy.BEST_EFFORT,
}


def _creation_error(topic: str, msg_type: str, exc: RuntimeError) -> BindingError:
    """rclpy's failure to create an endpoint, as the BindingError the server can report."""
    reason = str(exc).split(", at /", 1)[0]
    code = "TYPE_CLASH" if "incompatible type" in reason else "INTERNAL"
    return BindingError(code, f"rclpy cannot bind '{topic}' as {msg_type}: {reason}")


def qos_profile(qos: QoS) -> QoSProfile:
    """The rclpy profile of a binding: KEEP_LAST(depth), volatile, reliable or best effort.

    KEEP_LAST is what keeps a publisher from ever waiting on a slow reader; volatile matches
    the bridge's model (a late joiner gets the next value, not history).
    """
    reliability = _RELIABILITY.get(qos.reliability)
    if reliability is None:
        raise BindingError(
            "BAD_VALUE", f"QoS reliability '{qos.reliability}' is not 'reliable' or 'best_effort'"
        )
    if qos.depth < 1:
        raise BindingError("BAD_VALUE", f"QoS depth must be at least 1, not {qos.depth}")
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=qos.depth,
        reliability=reliability,
        durability=DurabilityPolicy.VOLATILE,
    )


@dataclass(eq=False)
class _Binding:
    """How many of this adapter's endpoints use a topic, and with which type."""

    msg_type: str
    users: int = 0


class Ros2Publisher:
    """A run-time-bound publisher (the thesis's RTBPublisher) on one ROS 2 topic."""

    def __init__(
        self, adapter: Ros2Adapter, topic: str, codec: ChannelCodec, ros: RclpyPublisher[Any]
    ) -> None:
        self.topic = topic
        self.spec: ValueSpec = codec.spec
        self.published = 0
        #: Messages rmw refused to publish ("cannot publish data"); each is logged and counted.
        self.failed = 0
        self._adapter = adapter
        self._encode = codec.encode
        self.ros = ros
        self._closed = False

    def publish(self, values: Sequence[Any]) -> None:
        """Encode every value (raising ``BindingError`` BAD_VALUE before any is sent), publish."""
        if self._closed:
            raise RuntimeError(f"publisher on {self.topic} is closed")
        encode = self._encode
        messages = [encode(v) for v in values]
        # The rclpy Publisher's own publish() enters the handle and type-checks per message;
        # the messages here are of the publisher's class by construction, so enter once per
        # batch (which also keeps a concurrent close() from destroying it mid-batch) and call
        # the handle directly: about a quarter less per message.
        handle = self.ros.handle
        sent = 0
        try:
            with handle:
                for msg in messages:
                    try:
                        handle.publish(msg)
                    except RCLError as exc:
                        # rmw refused this one message (Fast DDS in ASYNCHRONOUS mode does so
                        # when its history is full of unsent samples): a middleware condition,
                        # not the client's fault. Count it, keep the session and the batch.
                        self.failed += 1
                        if self.failed == 1 or self.failed % 1000 == 0:
                            reason = str(exc).split(", at /", 1)[0]
                            log.warning("ros2 publisher on %s: %s (%d messages refused so far)",
                                        self.topic, reason, self.failed)
                    else:
                        sent += 1
        except InvalidHandle:
            raise RuntimeError(f"publisher on {self.topic} is closed") from None
        finally:
            self.published += sent

    def stop(self) -> bool:
        """Refuse further publishes; ``True`` if it was open (the adapter then destroys it)."""
        was_open, self._closed = not self._closed, True
        return was_open

    def close(self) -> None:
        if self.stop():
            self._adapter.release_publisher(self)


class Ros2Subscription:
    """A topic listener: ROS 2 messages to the adapter callback, in batches, until closed."""

    def __init__(
        self, adapter: Ros2Adapter, topic: str, codec: ChannelCodec, callback: ValuesCallback
    ) -> None:
        self.topic = topic
        self.spec: ValueSpec = codec.spec
        #: Values handed to the callback, callbacks made, and callbacks that raised.
        self.delivered = 0
        self.batches = 0
        self.errors = 0
        self._adapter = adapter
        self._msg_cls = codec.msg_cls
        self._decode = codec.decode
        self._callback = callback
        # Held while the callback runs; close() takes it, so once close() returns the callback
        # is not running and will not run again.
        self._lock = threading.RLock()
        self._closed = False
        self.ros: RclpySubscription[Any] | None = None  # set by the adapter right after

    def on_message(self, msg: Any) -> None:
        """Executor thread: decode ``msg`` plus whatever is queued behind it, deliver once."""
        try:
            batch = [self._decode(msg)]
            self._drain(batch)
            with self._lock:
                if self._closed:
                    return
                self._callback(batch)
                self.delivered += len(batch)
                self.batches += 1
        except Exception:
            # The executor thread is shared by every subscription: one failing callback must
            # not stop delivery to the others, so log it with its traceback and count it.
            self.errors += 1
            log.exception("ros2 subscription on %s: delivering a batch failed", self.topic)

    def _drain(self, batch: list[Any]) -> None:
        ros = self.ros
        if ros is None:
            return
        decode, cls, handle = self._decode, self._msg_cls, ros.handle
        try:
            with handle:
                while len(batch) < MAX_BATCH:
                    taken: tuple[Any, Any] | None = handle.take_message(cls, False)
                    if taken is None:
                        return
                    batch.append(decode(taken[0]))
        except InvalidHandle:  # destroyed by close() on another thread: deliver what we have
            return

    def stop(self) -> bool:
        """Stop delivering (waits for a running callback); ``True`` if it was open."""
        with self._lock:
            was_open, self._closed = not self._closed, True
        return was_open

    def close(self) -> None:
        if self.stop():
            self._adapter.release_subscription(self)


class Ros2Adapter:
    """A :class:`~rlbridge.adapters.base.MiddlewareAdapter` on ROS 2, through rclpy.

    ``parameters`` are declared read-only on the node (``ros2 param get /rlbridge use_udp``);
    ``domain_id`` overrides ``ROS_DOMAIN_ID``. The executor thread starts here and stops in
    :meth:`close`; use the adapter as a context manager to make that explicit.
    """

    name = "ros2"

    def __init__(
        self,
        node_name: str = "rlbridge",
        namespace: str = "",
        *,
        parameters: Mapping[str, ParameterValue] | None = None,
        domain_id: int | None = None,
    ) -> None:
        self.catalog = MessageCatalog()
        self._lock = threading.RLock()
        self._bound: dict[str, _Binding] = {}
        self._publishers: set[Ros2Publisher] = set()
        self._subscriptions: set[Ros2Subscription] = set()
        self._closed = False
        self._context = Context()
        # args=[]: the adapter never reads the host program's command line (the server's CLI
        # flags are not ROS arguments); the ROS environment variables still apply.
        self._context.init(args=[], domain_id=domain_id)
        node: Node | None = None
        try:
            self.node = node = Node(
                node_name,
                namespace=namespace,
                context=self._context,
                use_global_arguments=False,
                start_parameter_services=True,
            )
            self._declare(parameters or {})
            self._me = (self.node.get_name(), self.node.get_namespace())
            # The node's own built-in topics (/rosout, /parameter_events): see _graph_types.
            self._builtin = {
                name for name, _ in self.node.get_publisher_names_and_types_by_node(*self._me)
            }
            self._executor = SingleThreadedExecutor(context=self._context)
            self._executor.add_node(self.node)
        except BaseException:
            if node is not None:
                node.destroy_node()
            self._context.try_shutdown()
            raise
        self._thread = threading.Thread(
            target=self._spin, name=f"rlbridge-ros2-{node_name}", daemon=True
        )
        self._thread.start()

    def __enter__(self) -> Ros2Adapter:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _declare(self, parameters: Mapping[str, ParameterValue]) -> None:
        # rcl_interfaces ships no type information; its ParameterDescriptor is all we need.
        descriptor_cls: Any = importlib.import_module("rcl_interfaces.msg").ParameterDescriptor
        for name, value in parameters.items():
            if not isinstance(value, bool | int | float | str):
                raise TypeError(f"parameter {name!r}: {type(value).__name__} is not a ROS scalar")
            descriptor = descriptor_cls(
                read_only=True, description="rlbridge server setting (fixed at start-up)"
            )
            self.node.declare_parameter(name, value, descriptor)

    def _spin(self) -> None:
        """The executor thread: run callbacks until close() (or the context) stops it."""
        try:
            self._executor.spin()
        except ExternalShutdownException:
            pass  # the context was shut down under us: nothing left to deliver
        except Exception:
            log.exception("ros2 executor thread died; subscriptions no longer deliver")

    # -- MiddlewareAdapter

    def resolve(self, msg_type: str, field: str | None) -> ValueSpec:
        return self.catalog.resolve(msg_type, field)

    def create_publisher(
        self, topic: str, msg_type: str, field: str | None, qos: QoS
    ) -> Ros2Publisher:
        codec = self.catalog.channel(msg_type, field)
        profile = qos_profile(qos)
        with self._lock:
            full = self._claim(topic, codec.spec.msg_type)
            try:
                ros = self.node.create_publisher(codec.msg_cls, full, profile)
            except RuntimeError as exc:  # rclpy's RCLError: rcl or rmw refused
                self._unclaim(full)
                raise _creation_error(full, codec.spec.msg_type, exc) from exc
            except BaseException:
                self._unclaim(full)
                raise
            pub = Ros2Publisher(self, full, codec, ros)
            self._publishers.add(pub)
        return pub

    def subscribe(
        self,
        topic: str,
        msg_type: str,
        field: str | None,
        qos: QoS,
        callback: ValuesCallback,
    ) -> Ros2Subscription:
        codec = self.catalog.channel(msg_type, field)
        profile = qos_profile(qos)
        with self._lock:
            full = self._claim(topic, codec.spec.msg_type)
            sub = Ros2Subscription(self, full, codec, callback)
            try:
                sub.ros = self.node.create_subscription(
                    codec.msg_cls, full, sub.on_message, profile
                )
            except RuntimeError as exc:  # rclpy's RCLError: rcl or rmw refused
                self._unclaim(full)
                raise _creation_error(full, codec.spec.msg_type, exc) from exc
            except BaseException:
                self._unclaim(full)
                raise
            self._subscriptions.add(sub)
        return sub

    def topics(self) -> list[tuple[str, str]]:
        """The ROS graph's topics as this node sees them, plus this adapter's own bindings."""
        with self._lock:
            if self._closed:
                return []
            found = {
                (name, msg_type)
                for name, _ in self.node.get_topic_names_and_types()
                for msg_type in self._graph_types(name)
            }
            found.update((name, b.msg_type) for name, b in self._bound.items())
        return sorted(found)

    def close(self) -> None:
        """Stop every endpoint, stop and join the executor thread, destroy node and context."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            subscriptions, publishers = list(self._subscriptions), list(self._publishers)
            self._subscriptions.clear()
            self._publishers.clear()
            self._bound.clear()
        for sub in subscriptions:
            sub.stop()
        for pub in publishers:
            pub.stop()
        self._executor.shutdown(timeout_sec=JOIN_TIMEOUT_S)
        if threading.current_thread() is not self._thread:
            self._thread.join(JOIN_TIMEOUT_S)
            if self._thread.is_alive():
                log.warning("ros2 executor thread did not stop within %.1f s", JOIN_TIMEOUT_S)
        self.node.destroy_node()
        self._context.try_shutdown()

    # -- bookkeeping (called with or without the lock; it is re-entrant)

    def full_topic_name(self, topic: str) -> str:
        """Expand ``topic`` against the node (relative names get the namespace) and check it."""
        try:
            full = expand_topic_name(topic, self.node.get_name(), self.node.get_namespace())
            validate_full_topic_name(full)
        except (InvalidTopicNameException, ValueError) as exc:
            reason = str(exc).split(" is invalid: ", 1)[-1].split(", at /", 1)[0]
            raise BindingError(
                "BAD_TOPIC", f"'{topic}' is not a valid ROS 2 topic name: {reason.strip()}"
            ) from None
        return full

    def _claim(self, topic: str, msg_type: str) -> str:
        """Check ``topic`` is free for ``msg_type`` here and in the graph; count one more user."""
        if self._closed:
            raise BindingError("INTERNAL", "the ros2 adapter is closed")
        full = self.full_topic_name(topic)
        own = self._bound.get(full)
        if own is not None and own.msg_type != msg_type:
            raise BindingError(
                "TYPE_CLASH",
                f"topic '{full}' is bound to {own.msg_type} by this bridge, not {msg_type}",
            )
        graph = self._graph_types(full)
        if graph and msg_type not in graph:
            raise BindingError(
                "TYPE_CLASH",
                f"topic '{full}' has type {', '.join(sorted(graph))} in the ROS graph, "
                f"not {msg_type}",
            )
        if own is None:
            own = self._bound[full] = _Binding(msg_type)
        own.users += 1
        return full

    def _graph_types(self, full: str) -> set[str]:
        """The types the ROS graph has on ``full``, minus this node's stale endpoints.

        rclpy destroys a closed publisher or subscription only when the executor thread next
        lets go of it (its event handlers sit in the executor's wait set), so for a moment after
        ``close()`` the graph still shows it. This adapter's own bindings are known exactly
        (``_bound``), so its node's endpoints count only on topics it still binds (or its
        built-in ones); endpoints of every other node count as the graph says.
        """
        infos = [
            *self.node.get_publishers_info_by_topic(full),
            *self.node.get_subscriptions_info_by_topic(full),
        ]
        own_count = full in self._bound or full in self._builtin
        return {
            info.topic_type
            for info in infos
            if own_count or (info.node_name, info.node_namespace) != self._me
        }

    def _unclaim(self, full: str) -> None:
        own = self._bound.get(full)
        if own is not None:
            own.users -= 1
            if own.users <= 0:
                del self._bound[full]

    def release_publisher(self, pub: Ros2Publisher) -> None:
        """Destroy a publisher (from its ``close()``), then forget its topic when unused."""
        with self._lock:
            if pub not in self._publishers:
                return  # the adapter is closed (or closing) and destroys it with the node
            self._publishers.discard(pub)
        self._on_executor_thread(lambda: self.node.destroy_publisher(pub.ros))
        with self._lock:
            self._unclaim(pub.topic)

    def release_subscription(self, sub: Ros2Subscription) -> None:
        """Destroy a subscription (from its ``close()``), then forget its topic when unused."""
        with self._lock:
            if sub not in self._subscriptions:
                return
            self._subscriptions.discard(sub)
        ros = sub.ros
        if ros is not None:
            self._on_executor_thread(lambda: self.node.destroy_subscription(ros))
        with self._lock:
            self._unclaim(sub.topic)

    def _on_executor_thread(self, action: Callable[[], object]) -> None:
        """Run ``action`` on the executor thread between two waits, and wait for it (bounded).

        rclpy defers destroying an entity the executor's current wait set holds (every
        subscription, and a publisher's event handlers) until the executor next wakes. Until
        then the DDS entity lives on, and binding its topic with another type fails inside
        rmw. Run on the executor thread, between waits, the destruction is immediate, so
        ``close()`` returns with the entity gone. The topic stays claimed meanwhile, and no
        lock is held while waiting, so a callback that binds does not deadlock with it.
        """
        if threading.current_thread() is self._thread or not self._thread.is_alive():
            action()  # in a callback (nothing is held) or with the executor already stopped
            return
        done = threading.Event()
        failure: list[BaseException] = []

        def run() -> None:
            try:
                action()
            except BaseException as exc:  # re-raised on the caller's thread below
                failure.append(exc)
            finally:
                done.set()

        self._executor.create_task(run)
        deadline = time.monotonic() + JOIN_TIMEOUT_S
        while not done.wait(0.05):
            if self._closed:
                return  # close() destroys the node and with it this entity
            if time.monotonic() > deadline:
                log.warning("ros2 executor did not get to a destroy within %.1f s", JOIN_TIMEOUT_S)
                return
        if failure:
            raise failure[0]
