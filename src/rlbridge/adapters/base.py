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
Durability = Literal["volatile", "transient_local", "match"]

#: Called with a batch of values, in order. Adapters may call it from any thread (the ROS 2
#: adapter calls it from its executor thread); the server hops to its event loop itself.
ValuesCallback = Callable[[Sequence[Any]], None]


@dataclass(frozen=True, slots=True)
class QoS:
    """The middleware's side of one binding: a ROS 2 QoS profile in three settings.

    ``reliability``: ``"reliable"`` or ``"best_effort"``; ``None`` (the default) lets the
    bridge choose by the channel's transport (best effort for UDP, reliable for TCP; an adapter
    given ``None`` directly uses reliable). ``depth``: the middleware's history (values kept
    per topic). ``durability``: ``"volatile"``; ``"transient_local"``: a publisher keeps its
    last ``depth`` values for late subscribers (a latched topic) and a subscription asks for
    them; ``"match"`` (subscribe only): take the durability and reliability of the publishers
    already on the topic, as ``ros2 topic echo`` does. The in-process bus ignores all three.
    Frozen: build one and pass it to every channel it fits.
    """

    reliability: Reliability | None = None
    depth: int = 10
    durability: Durability = "volatile"

    def __post_init__(self) -> None:
        # The words are rows of rlbridge.csp.option_table.RULES (a test keeps them equal).
        if self.reliability not in (None, "reliable", "best_effort"):
            raise ValueError(f"QoS: reliability={self.reliability!r} must be 'reliable', "
                             "'best_effort' or None (by transport)")
        if self.durability not in ("volatile", "transient_local", "match"):
            raise ValueError(f"QoS: durability={self.durability!r} must be 'volatile', "
                             "'transient_local' or 'match'")


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

    #: Values the middleware refused to take (the ROS 2 adapter's rmw errors); the server
    #: reports them per channel as ``ros_lost``.
    failed: int


@runtime_checkable
class Subscription(Protocol):
    """A topic listener: middleware messages to a callback, until closed."""

    def close(self) -> None:
        """Stop delivering; after it returns the callback is not called again."""

    #: Messages the middleware lost before delivering them (ROS 2: a full subscription
    #: queue, counted from sequence gaps); the server reports them per channel as ``ros_lost``.
    lost: int


class ServiceReply(Protocol):
    """How a provided service answers one request: exactly once, from any thread.

    ``send`` raises :class:`BindingError` (``BAD_VALUE``) for a response that does not fit
    the service's response type; the request then stays open for another answer or ``fail``.
    """

    def send(self, response: dict[str, Any]) -> None:
        """Answer with ``response`` (a dict of the response type's fields)."""

    def fail(self, reason: str) -> None:
        """The provider could not answer; the caller gets ``SERVICE_FAILED`` (or, on ROS 2,
        which has no error reply, no answer: its own timeout)."""


#: Called with a request (a dict) and its reply; may run on any thread and must not block.
ServiceHandler = Callable[[dict[str, Any], ServiceReply], None]


@runtime_checkable
class ServiceServer(Protocol):
    """A service provided through the middleware, until closed."""

    def close(self) -> None:
        """Stop serving; requests not answered yet fail (or, on ROS 2, go unanswered)."""


#: Called with each feedback message of a goal (a dict), on any thread.
GoalFeedback = Callable[[dict[str, Any]], None]
#: Called once when a goal ends: its final status (``GoalStatus``: 4 succeeded, 5 canceled,
#: 6 aborted) and its result (a dict), on any thread; 0 (unknown) and ``{}`` when the adapter
#: closed before the result came.
GoalDone = Callable[[int, dict[str, Any]], None]


@runtime_checkable
class GoalHandle(Protocol):
    """An accepted action goal."""

    def cancel(self) -> None:
        """Ask the action server to cancel it; the result then says whether it did."""


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

    def call_service(
        self, service: str, srv_type: str, request: dict[str, Any], timeout: float
    ) -> dict[str, Any]:
        """Call ``service`` and wait (at most ``timeout`` s) for the response; blocking.

        Raises :class:`BindingError`: ``UNKNOWN_TYPE`` (no such service type), ``BAD_VALUE``
        (the request does not fit it), ``BAD_TOPIC`` (not a service name), ``NO_SERVICE``
        (no server within the timeout), ``TIMEOUT`` (a server, but no answer) or
        ``SERVICE_FAILED`` (the server said it failed).
        """

    def serve_service(
        self, service: str, srv_type: str, handler: ServiceHandler
    ) -> ServiceServer:
        """Provide ``service``: ``handler`` gets each request; raise ``BindingError`` if not."""

    def services(self) -> list[tuple[str, str]]:
        """The services the middleware knows now, as ``(name, srv_type)`` sorted by name."""

    def send_goal(
        self, action: str, action_type: str, goal: dict[str, Any], feedback: GoalFeedback,
        done: GoalDone, timeout: float,
    ) -> GoalHandle:
        """Send an action goal; blocks until it is accepted (at most ``timeout`` s).

        Raises :class:`BindingError`: ``UNKNOWN_TYPE``, ``BAD_VALUE``, ``NO_SERVICE`` (no
        action server), ``TIMEOUT``, ``GOAL_REJECTED``. Feedback and the end come through
        the callbacks.
        """

    def close(self) -> None:
        """Close every publisher and subscription and release the middleware."""
