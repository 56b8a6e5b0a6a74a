"""The ROS 2 adapter: client channels bound at run time to rclpy publishers and subscriptions.

Theory of operation
-------------------
One adapter owns one ``rclpy.Context`` (never the global default context, so several adapters,
or a test and an adapter, coexist in one process), one node, and one executor spun in a thread
the adapter starts in its constructor and joins in :meth:`Ros2Adapter.close`: the ROS 2
counterpart of the thesis's asynchronous spinner (section 4.1.1), which replaced ROS 1's
``spinOnce()`` polling loop.

The thread is stopped by the adapter, not by ``Executor.shutdown()``: rclpy's shutdown sets a
flag, triggers the executor's own guard condition and destroys it at once, without waiting. An
executor thread that has checked the flag and is still building its wait set (it does so after
every callback, and for longer on a loaded machine) then waits without that guard, with no
timeout, and nothing ever wakes it: the thread outlives ``close()``. So the thread spins one
callback at a time until :meth:`Ros2Adapter.close` sets the adapter's own flag and triggers the
adapter's own guard condition (its own callback group, so it is in every wait set and is only
destroyed with the node, after the join); ``Executor.shutdown()`` runs after the join, when
there is no wait left to race with.

This module is that lifetime: the node, the executor thread, and creating and destroying
endpoints on them. What an endpoint does per value is in :mod:`.ros2_endpoints` (publishing on
the caller's thread, batched delivery on the executor thread); which topic may carry which type,
and the QoS profile, in :mod:`.ros2_topics`. Message types are resolved from their names at run
time (:mod:`.ros2_types`), which is what ROS 1's ShapeShifter did for the old bridge.

Importing this module imports rclpy (through :mod:`.ros2_rclpy`):
``rlbridge.adapters.load_adapter`` imports it lazily, and without rclpy the import fails with
an ``ImportError`` that says what to install.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any

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
from rlbridge.adapters.ros2_actions import Ros2Actions
from rlbridge.adapters.ros2_endpoints import MAX_BATCH, Ros2Publisher, Ros2Subscription
from rlbridge.adapters.ros2_rclpy import (
    Context,
    ExternalShutdownException,
    MutuallyExclusiveCallbackGroup,
    Node,
    SingleThreadedExecutor,
)
from rlbridge.adapters.ros2_services import Ros2Services
from rlbridge.adapters.ros2_topics import TopicClaims, creation_error, matching, qos_profile
from rlbridge.adapters.ros2_types import MessageCatalog

__all__ = ["JOIN_TIMEOUT_S", "MAX_BATCH", "ParameterValue", "Ros2Adapter", "Ros2Publisher",
           "Ros2Subscription", "qos_profile"]

log = logging.getLogger(__name__)

ParameterValue = bool | int | float | str

#: How long :meth:`Ros2Adapter.close` waits for the executor thread to stop.
JOIN_TIMEOUT_S = 5.0


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
        self.lock = threading.RLock()
        self._publishers: set[Ros2Publisher] = set()
        self._subscriptions: set[Ros2Subscription] = set()
        self._closed = False
        self._stopping = False  # set by close(): the executor thread's loop ends (module doc)
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
            self._claims = TopicClaims(self.node)
            self._services = Ros2Services(self)
            self._actions = Ros2Actions(self)
            # Triggered by close() to wake the executor thread out of its wait (module doc).
            self._wake = self.node.create_guard_condition(
                lambda: None, callback_group=MutuallyExclusiveCallbackGroup())
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
        executor = self._executor
        try:
            while not self._stopping and self._context.ok():
                executor.spin_once()
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
        with self.lock, self._claimed(topic, codec.spec.msg_type) as full:
            ros = self.node.create_publisher(codec.msg_cls, full, profile)
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
        if qos.durability == "match":
            qos = matching(qos, self.node.get_publishers_info_by_topic(
                self.full_topic_name(topic)))
        profile = qos_profile(qos)
        with self.lock, self._claimed(topic, codec.spec.msg_type) as full:
            sub = Ros2Subscription(self, full, codec, callback)
            sub.ros = self.node.create_subscription(codec.msg_cls, full, sub.on_message, profile)
            self._subscriptions.add(sub)
        return sub

    def topics(self) -> list[tuple[str, str]]:
        """The ROS graph's topics as this node sees them, plus this adapter's own bindings."""
        with self.lock:
            if self._closed:
                return []
            found = {
                (name, msg_type)
                for name, _ in self.node.get_topic_names_and_types()
                for msg_type in self._claims.graph_types(name)
            }
            found.update(self._claims.bound())
        return sorted(found)

    def call_service(
        self, service: str, srv_type: str, request: dict[str, Any], timeout: float
    ) -> dict[str, Any]:
        return self._services.call(service, srv_type, request, timeout)

    def serve_service(
        self, service: str, srv_type: str, handler: ServiceHandler
    ) -> ServiceServer:
        return self._services.serve(service, srv_type, handler)

    def services(self) -> list[tuple[str, str]]:
        with self.lock:
            return [] if self._closed else self._services.listing()

    def send_goal(
        self, action: str, action_type: str, goal: dict[str, Any], feedback: GoalFeedback,
        done: GoalDone, timeout: float,
    ) -> GoalHandle:
        return self._actions.send_goal(action, action_type, goal, feedback, done, timeout)

    def close(self) -> None:
        """Stop every endpoint, stop and join the executor thread, destroy node and context."""
        with self.lock:
            if self._closed:
                return
            self._closed = True
            subscriptions, publishers = list(self._subscriptions), list(self._publishers)
            self._subscriptions.clear()
            self._publishers.clear()
            self._claims.clear()
            self._services.clear()
            self._actions.clear()
        self._actions.end_running()
        for sub in subscriptions:
            sub.stop()
        for pub in publishers:
            pub.stop()
        # Flag first, then wake: a thread past the flag check waits on a triggered guard.
        self._stopping = True
        self._wake.trigger()
        if threading.current_thread() is not self._thread:
            self._thread.join(JOIN_TIMEOUT_S)
            if self._thread.is_alive():
                log.warning("ros2 executor thread did not stop within %.1f s", JOIN_TIMEOUT_S)
        self._executor.shutdown(timeout_sec=0)
        self.node.destroy_node()
        self._context.try_shutdown()

    # -- bookkeeping (called with or without the lock; it is re-entrant)

    def full_topic_name(self, topic: str) -> str:
        """Expand ``topic`` against the node (relative names get the namespace) and check it."""
        return self._claims.full_name(topic)

    def check_open(self) -> None:
        """Raise the ``BindingError`` of a closed adapter (called under the lock)."""
        if self._closed:
            raise BindingError("INTERNAL", "the ros2 adapter is closed")

    def release_service(self, provider: Any) -> None:
        """Destroy a provided service (from its ``close()``)."""
        with self.lock:
            if provider not in self._services.providers:
                return
            self._services.providers.discard(provider)
        ros = provider.ros
        if ros is not None:
            self._on_executor_thread(lambda: self.node.destroy_service(ros))

    @contextlib.contextmanager
    def _claimed(self, topic: str, msg_type: str) -> Iterator[str]:
        """Claim ``topic`` for the endpoint created in the block; a failure there undoes it."""
        if self._closed:
            raise BindingError("INTERNAL", "the ros2 adapter is closed")
        full = self._claims.claim(topic, msg_type)
        try:
            yield full
        except RuntimeError as exc:  # rclpy's RCLError: rcl or rmw refused
            self._claims.release(full)
            raise creation_error(full, msg_type, exc) from exc
        except BaseException:
            self._claims.release(full)
            raise

    def release_publisher(self, pub: Ros2Publisher) -> None:
        """Destroy a publisher (from its ``close()``), then forget its topic when unused."""
        with self.lock:
            if pub not in self._publishers:
                return  # the adapter is closed (or closing) and destroys it with the node
            self._publishers.discard(pub)
        self._on_executor_thread(lambda: self.node.destroy_publisher(pub.ros))
        with self.lock:
            self._claims.release(pub.topic)

    def release_subscription(self, sub: Ros2Subscription) -> None:
        """Destroy a subscription (from its ``close()``), then forget its topic when unused."""
        with self.lock:
            if sub not in self._subscriptions:
                return
            self._subscriptions.discard(sub)
        ros = sub.ros
        if ros is not None:
            self._on_executor_thread(lambda: self.node.destroy_subscription(ros))
        with self.lock:
            self._claims.release(sub.topic)

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
