"""Wire error codes become exceptions through one table; messages say who is at fault."""

from __future__ import annotations

import pytest

from rlbridge import ErrorCode, LocalProtocolError, RemoteError, RemoteProtocolError
from rlbridge.errors import (
    AuthenticationFailed,
    BadValueError,
    BindingRefused,
    LimitExceeded,
    NoSuchFieldError,
    RlbridgeError,
    ServerShuttingDown,
    TypeClashError,
    UnknownTypeError,
    error_from_code,
)


@pytest.mark.parametrize(
    ("code", "cls"),
    [
        (ErrorCode.UNKNOWN_TYPE, UnknownTypeError),
        (ErrorCode.PACKAGE_MISSING, UnknownTypeError),
        (ErrorCode.TYPE_CLASH, TypeClashError),
        (ErrorCode.NO_SUCH_FIELD, NoSuchFieldError),
        (ErrorCode.BAD_TOPIC, BindingRefused),
        (ErrorCode.CHANNEL_IN_USE, BindingRefused),
        (ErrorCode.TRANSPORT_DISABLED, BindingRefused),
        (ErrorCode.BAD_VALUE, BadValueError),
        (ErrorCode.LIMIT, LimitExceeded),
        (ErrorCode.AUTH_FAILED, AuthenticationFailed),
        (ErrorCode.NOT_ALLOWED, AuthenticationFailed),
        (ErrorCode.SHUTTING_DOWN, ServerShuttingDown),
        (ErrorCode.INTERNAL, RemoteError),
        (ErrorCode.MALFORMED, RemoteError),
    ],
)
def test_code_to_exception(code: ErrorCode, cls: type[RemoteError]) -> None:
    exc = error_from_code(int(code), "what went wrong", channel=7)
    assert type(exc) is cls
    assert exc.code is code
    assert exc.reason == "what went wrong"
    assert exc.channel == 7
    assert str(exc) == f"what went wrong [{code.name}]"
    assert isinstance(exc, RlbridgeError)


def test_unknown_code_keeps_its_number() -> None:
    exc = error_from_code(999, "from the future")
    assert type(exc) is RemoteError
    assert exc.code == 999
    assert str(exc) == "from the future [999]"


def test_fault_axes_are_separate() -> None:
    remote = RemoteProtocolError(ErrorCode.TOO_LARGE, "too big", fatal=True)
    assert (remote.code, remote.reason, remote.fatal) == (ErrorCode.TOO_LARGE, "too big", True)
    assert not RemoteProtocolError(ErrorCode.MALFORMED, "x").fatal
    for cls in (LocalProtocolError, RemoteProtocolError, RemoteError):
        assert issubclass(cls, RlbridgeError)
    assert not issubclass(RemoteProtocolError, RemoteError)
    assert not issubclass(LocalProtocolError, RemoteProtocolError)


def test_codes_are_stable() -> None:
    """Codes are on the wire: renumbering one breaks every deployed peer."""
    assert {c.name: c.value for c in ErrorCode} == {
        "UNSUPPORTED_VERSION": 1, "MALFORMED": 2, "TOO_LARGE": 3, "UNEXPECTED": 4,
        "UNKNOWN_TYPE": 10, "TYPE_CLASH": 11, "NO_SUCH_FIELD": 12, "BAD_VALUE": 13,
        "UNKNOWN_CHANNEL": 14, "CHANNEL_IN_USE": 15, "BAD_TOPIC": 16, "PACKAGE_MISSING": 17,
        "LIMIT": 20, "AUTH_FAILED": 21, "NOT_ALLOWED": 22, "TRANSPORT_DISABLED": 23,
        "SHUTTING_DOWN": 30, "INTERNAL": 31,
        "NO_SERVICE": 40, "TIMEOUT": 41, "SERVICE_FAILED": 42, "GOAL_REJECTED": 43,
    }
