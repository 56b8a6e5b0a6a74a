"""What the ROS 2 adapter may bind, and how: topic names, their types, the QoS profile.

A topic carries one type. The adapter checks that twice before it creates an endpoint: against
its own bindings, known exactly, and against the ROS graph, which lags behind (see
:meth:`TopicClaims.graph_types`). A refusal is a :class:`BindingError` whose code the server
sends to the client as is.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from rlbridge.adapters.base import BindingError, QoS
from rlbridge.adapters.ros2_rclpy import (
    DurabilityPolicy,
    HistoryPolicy,
    InvalidTopicNameException,
    Node,
    QoSProfile,
    ReliabilityPolicy,
    expand_topic_name,
    validate_full_topic_name,
)

_RELIABILITY: Mapping[str, ReliabilityPolicy] = {
    "reliable": ReliabilityPolicy.RELIABLE,
    "best_effort": ReliabilityPolicy.BEST_EFFORT,
}


def creation_error(topic: str, msg_type: str, exc: RuntimeError) -> BindingError:
    """rclpy's failure to create an endpoint, as the BindingError the server can report."""
    reason = str(exc).split(", at /", 1)[0]
    code = "TYPE_CLASH" if "incompatible type" in reason else "INTERNAL"
    return BindingError(code, f"rclpy cannot bind '{topic}' as {msg_type}: {reason}")


_DURABILITY: Mapping[str, DurabilityPolicy] = {
    "volatile": DurabilityPolicy.VOLATILE,
    "transient_local": DurabilityPolicy.TRANSIENT_LOCAL,
}


def matching(qos: QoS, publishers: Sequence[Any]) -> QoS:
    """``durability="match"``: the QoS a subscription needs to hear every publisher found,
    as ``ros2 topic echo`` chooses it: transient local and reliable only if all of them are
    (a transient-local reader does not match a volatile writer; a reliable reader does not
    match a best-effort writer). No publisher yet: volatile, and the reliability asked for.
    """
    if not publishers:
        return QoS(qos.reliability, qos.depth, "volatile")
    profiles = [p.qos_profile for p in publishers]
    latched = all(p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in profiles)
    reliable = all(p.reliability == ReliabilityPolicy.RELIABLE for p in profiles)
    return QoS("reliable" if reliable else "best_effort", qos.depth,
               "transient_local" if latched else "volatile")


def qos_profile(qos: QoS) -> QoSProfile:
    """The rclpy profile of a binding: KEEP_LAST(depth), reliable or best effort, volatile
    or transient local (``match`` is resolved by :func:`matching` first).

    KEEP_LAST is what keeps a publisher from ever waiting on a slow reader; volatile is the
    bridge's default model (a late joiner gets the next value, not history); transient local
    makes a latched topic (a map, a robot description): a late joiner gets the last ``depth``.
    """
    durability = _DURABILITY.get(qos.durability)
    if durability is None:
        raise BindingError("BAD_VALUE", f"QoS durability '{qos.durability}' is not 'volatile' "
                           "or 'transient_local' here")
    reliability = _RELIABILITY.get(qos.reliability or "reliable")
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
        durability=durability,
    )


@dataclass(eq=False)
class _Binding:
    """How many of this adapter's endpoints use a topic, and with which type."""

    msg_type: str
    users: int = 0


class TopicClaims:
    """The topics one node's endpoints use, each with its type and count of users.

    Not locked itself: the adapter calls it under its own lock.
    """

    def __init__(self, node: Node) -> None:
        self._node = node
        self._me = (node.get_name(), node.get_namespace())
        # The node's own built-in topics (/rosout, /parameter_events): see graph_types.
        self._builtin = {name for name, _ in node.get_publisher_names_and_types_by_node(*self._me)}
        self._bound: dict[str, _Binding] = {}

    def full_name(self, topic: str) -> str:
        """Expand ``topic`` against the node (relative names get the namespace) and check it."""
        node = self._node
        try:
            full = expand_topic_name(topic, node.get_name(), node.get_namespace())
            validate_full_topic_name(full)
        except (InvalidTopicNameException, ValueError) as exc:
            reason = str(exc).split(" is invalid: ", 1)[-1].split(", at /", 1)[0]
            raise BindingError(
                "BAD_TOPIC", f"'{topic}' is not a valid ROS 2 topic name: {reason.strip()}"
            ) from None
        return full

    def claim(self, topic: str, msg_type: str) -> str:
        """Check ``topic`` is free for ``msg_type`` here and in the graph; count one more user."""
        full = self.full_name(topic)
        own = self._bound.get(full)
        if own is not None and own.msg_type != msg_type:
            raise BindingError(
                "TYPE_CLASH",
                f"topic '{full}' is bound to {own.msg_type} by this bridge, not {msg_type}",
            )
        graph = self.graph_types(full)
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

    def release(self, full: str) -> None:
        """One user fewer on ``full``; the last one frees the topic for another type."""
        own = self._bound.get(full)
        if own is not None:
            own.users -= 1
            if own.users <= 0:
                del self._bound[full]

    def clear(self) -> None:
        """Forget every claim (the adapter is closing and destroys the node with them)."""
        self._bound.clear()

    def bound(self) -> Iterator[tuple[str, str]]:
        """``(topic, type)`` of every topic this adapter binds now."""
        return ((name, b.msg_type) for name, b in self._bound.items())

    def graph_types(self, full: str) -> set[str]:
        """The types the ROS graph has on ``full``, minus this node's stale endpoints.

        rclpy destroys a closed publisher or subscription only when the executor thread next
        lets go of it (its event handlers sit in the executor's wait set), so for a moment after
        ``close()`` the graph still shows it. This adapter's own bindings are known exactly
        (``_bound``), so its node's endpoints count only on topics it still binds (or its
        built-in ones); endpoints of every other node count as the graph says.
        """
        node = self._node
        infos = [
            *node.get_publishers_info_by_topic(full),
            *node.get_subscriptions_info_by_topic(full),
        ]
        own_count = full in self._bound or full in self._builtin
        return {
            info.topic_type
            for info in infos
            if own_count or (info.node_name, info.node_namespace) != self._me
        }
