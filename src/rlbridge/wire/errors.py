"""Error codes on the wire and the exceptions they become, in one table.

Two axes, as in h11 and trio: *who is at fault* (``LocalProtocolError``: this program misused
the API; ``RemoteProtocolError``: the peer sent bytes that are not our protocol) and *what the
peer reported* (:class:`RemoteError` and its subclasses, raised from an error packet's code).
"""

from __future__ import annotations

from enum import IntEnum


class ErrorCode(IntEnum):
    """Numeric codes carried by error packets; stable across versions (see docs/protocol.md)."""

    UNSUPPORTED_VERSION = 1
    MALFORMED = 2
    TOO_LARGE = 3
    UNEXPECTED = 4
    UNKNOWN_TYPE = 10
    TYPE_CLASH = 11
    NO_SUCH_FIELD = 12
    BAD_VALUE = 13
    UNKNOWN_CHANNEL = 14
    CHANNEL_IN_USE = 15
    BAD_TOPIC = 16
    PACKAGE_MISSING = 17
    LIMIT = 20
    AUTH_FAILED = 21
    NOT_ALLOWED = 22
    TRANSPORT_DISABLED = 23
    SHUTTING_DOWN = 30
    INTERNAL = 31
    NO_SERVICE = 40
    TIMEOUT = 41
    SERVICE_FAILED = 42
    GOAL_REJECTED = 43


class RlbridgeError(Exception):
    """Base of every exception rlbridge raises on purpose."""


class LocalProtocolError(RlbridgeError):
    """This side tried to do something the protocol does not allow (a bug in the caller)."""


class RemoteProtocolError(RlbridgeError):
    """The peer sent something that is not valid rlbridge protocol.

    ``code`` says what kind of invalid (malformed, too large, wrong version); ``fatal`` is true
    when the byte stream can no longer be trusted (framing lost) and the connection must close.
    """

    def __init__(self, code: ErrorCode, reason: str, *, fatal: bool = False) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason
        self.fatal = fatal
        #: What could be salvaged from an invalid body: its tag and channel id (when the body
        #: is at least a MessagePack array starting with two integers), so a refused
        #: topic-connect can still be answered with a TopicError for its channel.
        self.tag: int | None = None
        self.channel: int | None = None
        #: The session token of a datagram whose header was valid but whose body was not.
        self.token: int | None = None


class RemoteError(RlbridgeError):
    """The peer answered with an error packet; ``code`` and ``reason`` are what it said."""

    def __init__(self, code: int, reason: str, *, channel: int | None = None) -> None:
        try:
            self.code: ErrorCode | int = ErrorCode(code)
        except ValueError:
            self.code = code
        self.reason = reason
        self.channel = channel
        name = self.code.name if isinstance(self.code, ErrorCode) else str(code)
        super().__init__(f"{reason} [{name}]")


class BindingRefused(RemoteError):
    """The server refused a topic-connect: bad type, field, topic or clash."""


class UnknownTypeError(BindingRefused):
    """The middleware does not know the message type."""


class TypeClashError(BindingRefused):
    """The topic exists with another message type."""


class NoSuchFieldError(BindingRefused):
    """The message type has no such field."""


class BadValueError(RemoteError):
    """A value did not match its channel's field type."""


class LimitExceeded(RemoteError):
    """A server limit (sessions, channels, packet size, rate) was reached."""


class AuthenticationFailed(RemoteError):
    """The server refused the client's credentials or network."""


class ServerShuttingDown(RemoteError):
    """The server is stopping; reconnect later."""


class ServiceError(RemoteError):
    """A service call failed; the subclass says how."""


class NoServiceError(ServiceError):
    """No server provides the service (within the call's timeout)."""


class ServiceTimeout(ServiceError, TimeoutError):
    """The service has a server, but it did not answer within the call's timeout."""


class ServiceFailed(ServiceError):
    """The server failed to answer (it said so, or its answer did not fit the type)."""


class GoalRejected(ServiceError):
    """The action server rejected the goal."""


_BY_CODE: dict[int, type[RemoteError]] = {
    ErrorCode.UNKNOWN_TYPE: UnknownTypeError,
    ErrorCode.PACKAGE_MISSING: UnknownTypeError,
    ErrorCode.TYPE_CLASH: TypeClashError,
    ErrorCode.NO_SUCH_FIELD: NoSuchFieldError,
    ErrorCode.BAD_TOPIC: BindingRefused,
    ErrorCode.CHANNEL_IN_USE: BindingRefused,
    ErrorCode.TRANSPORT_DISABLED: BindingRefused,
    ErrorCode.BAD_VALUE: BadValueError,
    ErrorCode.LIMIT: LimitExceeded,
    ErrorCode.AUTH_FAILED: AuthenticationFailed,
    ErrorCode.NOT_ALLOWED: AuthenticationFailed,
    ErrorCode.SHUTTING_DOWN: ServerShuttingDown,
    ErrorCode.NO_SERVICE: NoServiceError,
    ErrorCode.TIMEOUT: ServiceTimeout,
    ErrorCode.SERVICE_FAILED: ServiceFailed,
    ErrorCode.GOAL_REJECTED: GoalRejected,
}


def error_from_code(code: int, reason: str, *, channel: int | None = None) -> RemoteError:
    """The exception an error packet with ``code`` becomes on the receiving side."""
    return _BY_CODE.get(code, RemoteError)(code, reason, channel=channel)
