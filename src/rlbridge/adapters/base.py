"""The contract between the bridge server and a middleware.

The server never imports a middleware library: it talks to this small Protocol, and each
middleware (the in-process bus, ROS 2 through rclpy) implements it. Keeping the surface small
is what makes the shared conformance suite (``tests/adapters/contract.py``) possible.

Values cross this boundary already validated and in plain Python form: a field-bound channel
carries scalars (``float``, ``int``, ``bool``, ``str``), a whole-message channel carries a
``dict`` with ROS field names (nested messages as nested dicts). Batches are sequences, so one
network packet with a thousand values costs one call, not a thousand.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol, runtime_checkable

Reliability = Literal["reliable", "best_effort"]

#: Called with a batch of values, in order. Adapters may call it from any thread (the ROS 2
#: adapter calls it from its executor thread); the server hops to its event loop itself.
ValuesCallback = Callable[[Sequence[Any]], None]


@dataclass(frozen=True, slots=True)
class QoS:
    """Delivery settings for one binding (ROS 2 QoS subset; the in-process bus ignores them)."""

    reliability: Reliability = "reliable"
    depth: int = 10


@dataclass(frozen=True, slots=True)
class ValueSpec:
    """What one channel carries, resolved from a message type and a field path.

    ``python_type`` is a type msgspec can validate against (``float``, ``Annotated[int, Meta]``,
    a ``msgspec.Struct`` for a whole message, ...); ``default`` is the value a fresh message has
    in that field, which is what a non-blocking reader starts from.
    """

    msg_type: str
    field: str | None
    python_type: Any
    default: Any


class BindingError(Exception):
    """A topic binding the middleware cannot make; ``code`` is a wire error code name.

    Raised for an unknown message type, a type clash on a topic, a field the type lacks, or a
    value of the wrong kind. The server turns it into a topic-error packet; the session lives on.
    """

    def __init__(self, code: str, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


@runtime_checkable
class Publisher(Protocol):
    """A run-time-bound publisher: client values into one middleware topic."""

    def publish(self, values: Sequence[Any]) -> None:
        """Publish each value (field value or whole-message dict) as one message, in order.

        A value the middleware cannot publish raises ``BindingError("BAD_VALUE")`` before
        any value of the call is published (the server then retries value by value).
        """

    def close(self) -> None:
        """Release the publisher; further publishes are a programming error."""


@runtime_checkable
class Subscription(Protocol):
    """A topic listener: middleware messages to a callback, until closed."""

    def close(self) -> None:
        """Stop delivering; after it returns the callback is not called again."""


@runtime_checkable
class MiddlewareAdapter(Protocol):
    """What the server needs from a middleware; see the module docstring."""

    name: str

    def resolve(self, msg_type: str, field: str | None) -> ValueSpec:
        """Check a message type and field path; raise :class:`BindingError` if unusable."""

    def create_publisher(
        self, topic: str, msg_type: str, field: str | None, qos: QoS
    ) -> Publisher:
        """Bind a publisher to ``topic``; raise :class:`BindingError` on a type clash."""

    def subscribe(
        self,
        topic: str,
        msg_type: str,
        field: str | None,
        qos: QoS,
        callback: ValuesCallback,
    ) -> Subscription:
        """Listen on ``topic``, calling ``callback`` with the channel's values (field or dict)."""

    def topics(self) -> list[tuple[str, str]]:
        """The topics the middleware knows now, as ``(name, msg_type)`` sorted by name."""

    def close(self) -> None:
        """Close every publisher and subscription and release the middleware."""
