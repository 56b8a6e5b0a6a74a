"""Every exception rlbridge raises on purpose, in one hierarchy (``from rlbridge import ...``).

``except RlbridgeError`` catches all of them. Below the root, one branch per thing that can go
wrong, so code catches what it can act on:

=====================  ======================================================================
:class:`SessionError`  the session with the server: could not open (:class:`ConnectionFailed`,
                       :class:`AuthenticationFailed`, :class:`TlsFailed`), or ended
                       (:class:`ConnectionClosed`, :class:`ServerShuttingDown`)
:class:`ChannelError`  one channel: closed, empty, would block, misused, link lost
:class:`BindingRefused`  the server refused a topic binding: type, field, topic, clash
:class:`ValueRejected`   a value that cannot go: wrong type here, refused there, over a limit
:class:`ServiceError`  a service call, action goal or parameter request failed
:class:`ProtocolError` bytes that are not rlbridge's protocol (a bug on one side)
=====================  ======================================================================

An error the server reported is also a :class:`RemoteError` (``code``, ``reason``: what the
error packet said; :class:`ErrorCode` lists the codes, docs/protocol.md). Misuse of a call
(a bad option, a wrong argument type) stays a plain ``ValueError``/``TypeError``: the message
names the option and says why. Every message here says what to do next.

This module imports nothing of rlbridge: the sans-IO wire layer raises these too.
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
    """Root of every exception rlbridge raises on purpose: catch this to catch them all."""


class RealTimeWarning(RuntimeWarning):
    """A hard-real-time rule could not be honoured (a blocking read in a loop marked ``hrt``,
    no real-time scheduling, memory not locked); the loop runs on, with weaker timing.

    A warning, not an error: filter it with :mod:`warnings` once the trade-off is deliberate.
    """


# -- the server said so ------------------------------------------------------------------------
class RemoteError(RlbridgeError):
    """The server answered with an error packet; ``code`` and ``reason`` are what it said.

    ``channel`` is the channel id the error is about (``None``: the session).
    """

    def __init__(self, code: int, reason: str, *, channel: int | None = None) -> None:
        try:
            self.code: ErrorCode | int = ErrorCode(code)
        except ValueError:
            self.code = code
        self.reason = reason
        self.channel = channel
        name = self.code.name if isinstance(self.code, ErrorCode) else str(code)
        super().__init__(f"{reason} [{name}]")


# -- protocol ----------------------------------------------------------------------------------
class ProtocolError(RlbridgeError):
    """Something that is not rlbridge's protocol: a bug in this program or in the peer."""


class LocalProtocolError(ProtocolError):
    """This side tried to do something the protocol does not allow (a bug in the caller)."""


class RemoteProtocolError(ProtocolError):
    """The peer sent something that is not valid rlbridge protocol.

    ``code`` says what kind of invalid (malformed, too large, wrong version); ``fatal`` is true
    when the byte stream can no longer be trusted (framing lost) and the connection must close.
    Check that both ends run the same rlbridge version (``rlbridge --version``).
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


# -- the session -------------------------------------------------------------------------------
class SessionError(RlbridgeError):
    """The session with the bridge server could not open, or ended."""


class ConnectionFailed(SessionError):
    """The bridge server could not be reached or refused the session.

    The message says where and why; check that ``rlbridge serve`` runs there (``rlbridge ping
    HOST:PORT``) and that both ends agree on security (PSK, TLS).
    """


class ConnectionClosed(SessionError):
    """The session is over (closed by this program, the server, or the watchdog).

    With ``reconnect`` on, a session that ends is opened again by itself; this is raised once
    the bridge is closed for good: connect a new :class:`~rlbridge.Bridge`.
    """


class AuthenticationFailed(RemoteError, SessionError):
    """The server refused the client's credentials or network (``code`` says which).

    Retrying with the same key will not help: use the key the server has for this client's
    ``name`` (``rlbridge serve --psk-file``), or ask for its network to be allowed.
    """


class AuthRefused(ConnectionFailed, AuthenticationFailed):
    """Authentication failed while the session opened: a :class:`ConnectionFailed` and an
    :class:`AuthenticationFailed`, so code catching either sees it."""


class TlsError(SessionError):
    """A TLS set-up or check failed; the message says which file or which check, and why."""


class TlsFailed(ConnectionFailed, TlsError):
    """TLS could not be set up for a session: certificate, fingerprint, or a server without TLS.

    Retrying with the same settings will not help; the message says what to change.
    """


class NoCipher(SessionError):
    """``$RLBRIDGE_AEAD`` asks for a ChaCha20-Poly1305 that cannot be had: nothing can seal.

    Unset ``$RLBRIDGE_AEAD``, or install what it names (libsodium-dev, then reinstall).
    """


class ServerShuttingDown(RemoteError, SessionError):
    """The server is stopping; a bridge with ``reconnect`` on opens a new session later."""


# -- channels ----------------------------------------------------------------------------------
class ChannelError(RlbridgeError):
    """Base class of every channel error; ``channel`` is the channel's name."""

    def __init__(self, channel: str, message: str) -> None:
        super().__init__(message)
        self.channel = channel


class ChannelClosed(ChannelError):
    """The channel was closed (``close()``, ``bridge.unsubscribe``, ``bridge.close()``).

    Raised by writes after the close, by reads once a closed channel has no buffered
    value left, and in every party that was blocked on the channel when it closed.
    """

    def __init__(self, channel: str) -> None:
        super().__init__(channel, f"channel {channel!r} is closed: nothing more comes through "
                                  "it; make a new one (bridge.subscribe/publish) to go on")


class WouldBlock(ChannelError):
    """A ``try_*`` call could not complete without waiting: nothing new to read, or no room.

    Try again later, or call the blocking twin (``read``/``write``) with a timeout.
    """

    def __init__(self, channel: str, operation: str) -> None:
        super().__init__(channel, f"{operation} on channel {channel!r} would block: try again "
                                  f"later, or call the blocking {operation.removeprefix('try_')}")
        self.operation = operation


class NoValueYet(ChannelError, LookupError):
    """A non-blocking channel without ``initial`` was read before any value arrived."""

    def __init__(self, channel: str) -> None:
        super().__init__(
            channel,
            f"non-blocking channel {channel!r} has never received a value and has no "
            "initial value: give it one where it is made, bridge.subscribe(..., initial=0.0) "
            "(or Channel(..., initial=...)), or catch NoValueYet until the first value",
        )


class ChannelMisuseError(ChannelError, RuntimeError):
    """A channel was used in a way it cannot mean anything.

    Two threads used the same end of a one-to-one buffered channel at the same time (the
    rings are lock-free single-producer/single-consumer: two writers would lose or duplicate
    values without a trace, so the overlap is refused), or a verb was used on a direction that
    has no such end (``read`` on an outgoing channel). ``end`` is ``"writer"`` or ``"reader"``.
    """

    def __init__(self, channel: str, end: str, message: str | None = None) -> None:
        super().__init__(
            channel,
            message or
            f"two threads used the {end} end of buffered channel {channel!r} concurrently; "
            f"a buffered channel has exactly one {end} at a time (use one channel per "
            "writer, or an MpscRing to fan several writers in)",
        )
        self.end = end


class SecondWriterError(ChannelMisuseError):
    """A second thread wrote an outgoing channel whose first writer thread is still alive."""

    def __init__(self, topic: str, owner: int, intruder: int) -> None:
        super().__init__(
            f"{topic} out", "writer",
            f"outgoing channel {topic!r} is written by thread {owner}; thread {intruder} "
            "wrote it too. Its ring buffer has a single producer: two writers would lose "
            "values without a trace. Publish one channel per writer thread, or hand values "
            "to the one writer through a local Channel.")


class LinkLost(ChannelError):
    """Read from a channel with ``Policy(on_lost="raise")`` while the link is lost."""

    def __init__(self, channel: str) -> None:
        super().__init__(channel, f"channel {channel!r}: the link to the bridge server is "
                                  "lost (on_lost='raise'); the SDK is reconnecting: hold the "
                                  "actuators safe and read again later")


# -- bindings ----------------------------------------------------------------------------------
class BindingRefused(RemoteError):
    """The server refused a topic binding (subscribe/publish): type, field, topic or clash.

    The reason names what to change; ``rlbridge topic list`` shows the topics and their types.
    """


class UnknownTypeError(BindingRefused):
    """The middleware does not know the message type (spelled ``pkg/msg/Type``; is the
    package installed and sourced where the server runs?)."""


class TypeClashError(BindingRefused):
    """The topic exists with another message type: use that type, or another topic."""


class NoSuchFieldError(BindingRefused):
    """The message type has no such field (``field=None`` binds whole messages)."""


# -- values ------------------------------------------------------------------------------------
class ValueRejected(RlbridgeError):
    """A value could not go: wrong for its field here, refused by the server, or over a limit."""


class WrongValueType(ValueRejected, LocalProtocolError, TypeError):
    """``write`` was given a value that cannot be the bound field's type.

    A ``TypeError`` too (this program's mistake, caught before it reaches the network).
    ``topic``, ``msg_type`` and ``field`` name the channel (``field`` ``None``: whole
    messages), ``path`` the part of a whole message that is wrong (``"linear.x"``),
    ``expected`` what the type needs and ``value`` what was given.
    """

    def __init__(self, topic: str, msg_type: str, field: str | None, path: str,
                 expected: str, value: object) -> None:
        self.topic = topic
        self.msg_type = msg_type
        self.field = field
        self.path = path
        self.expected = expected
        self.value = value
        where = field if field else "<whole message>"
        if path:
            where = path if not field else f"{field}.{path}"
        shown = repr(value)
        shown = shown if len(shown) <= 60 else shown[:57] + "..."
        super().__init__(f"topic {topic!r} ({msg_type} field {where}) needs {expected}, "
                         f"got {type(value).__name__} {shown}: convert it before writing")


class BadValueError(RemoteError, ValueRejected):
    """The server refused a value that did not match its channel's field type."""


class LimitExceeded(RemoteError, ValueRejected):
    """A server limit (sessions, channels, packet size, rate) was reached: send less, or raise
    the limit where the server starts (``rlbridge serve --help``)."""


# -- services, actions, parameters -------------------------------------------------------------
class ServiceError(RlbridgeError):
    """A service call, an action goal or a parameter request failed; the subclass says how."""


class NoServiceError(RemoteError, ServiceError):
    """No server provides the service (within the call's timeout): is its node running?
    (``rlbridge service list``)."""


class ServiceTimeout(RemoteError, ServiceError, TimeoutError):
    """The service has a server, but it did not answer within the call's timeout: give it a
    longer ``timeout``, or check the node that serves it."""


class ServiceFailed(RemoteError, ServiceError):
    """The server failed to answer (it said so, or its answer did not fit the type)."""


class GoalRejected(RemoteError, ServiceError):
    """The action server rejected the goal: check the goal's values against what it accepts."""


class ParameterError(ServiceError):
    """A node has no such parameter, refused a new value, or the value has no ROS type."""


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
