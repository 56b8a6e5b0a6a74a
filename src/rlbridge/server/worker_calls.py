"""Blocking middleware work for a session: off the event loop, back with its outcome.

``adapter.call_service`` and ``adapter.send_goal`` block (discovery, the answer, the action
server's acceptance), so a service call (:mod:`~rlbridge.server.services`) and a goal
(:mod:`~rlbridge.server.actions`) both run on the server's worker pool and hand their future
back to the loop thread, where the session's state lives. Both turn a failure into a wire code
the same way: a ``BindingError`` carries its own code; anything else is ``INTERNAL``, logged
with its traceback, and named by its type in the reason.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from rlbridge.adapters.base import BindingError
from rlbridge.wire import ErrorCode, TopicError

if TYPE_CHECKING:
    from rlbridge.server.context import ServerContext

log = logging.getLogger("rlbridge.server")

T = TypeVar("T")

#: The longest a call or a goal's acceptance may hold a worker thread (a longer timeout is cut).
MAX_TIMEOUT_S = 300.0


def timeout_s(timeout_ms: int) -> float:
    """A packet's ``timeout_ms`` in seconds, at most :data:`MAX_TIMEOUT_S`."""
    return min(timeout_ms / 1000, MAX_TIMEOUT_S)


def error_code(name: str) -> ErrorCode:
    """The wire code of a ``BindingError`` code name (``INTERNAL`` for an unknown one)."""
    return ErrorCode.__members__.get(name, ErrorCode.INTERNAL)


@dataclass(frozen=True)
class Failure:
    """Why blocking work failed, as the wire says it: a code and a reason (the packet that
    carries it cuts it, wire/packets.py)."""

    code: ErrorCode
    reason: str


def off_loop(ctx: ServerContext, then: Callable[[Future[T]], None], work: Callable[..., T],
             *args: Any) -> Future[T]:
    """Run ``work(*args)`` on the worker pool; ``then(future)`` on the loop thread when done."""
    future = ctx.workers.submit(work, *args)
    loop = ctx.loop
    future.add_done_callback(lambda f: loop.call_soon_threadsafe(then, f))
    return future


def outcome(future: Future[T], what: str) -> T | Failure:
    """The result of finished blocking work, or its :class:`Failure` (``what`` names it in
    the log: ``service call to /arm/enable``)."""
    try:
        return future.result()
    except BindingError as exc:
        return Failure(error_code(exc.code), exc.reason)
    except Exception as exc:
        log.exception("%s failed", what)
        return Failure(ErrorCode.INTERNAL, f"{type(exc).__name__}: {exc}")


def channel_in_use(channel: int) -> TopicError:
    """The refusal of a goal or an offer on a channel this session already uses."""
    return TopicError(channel, int(ErrorCode.CHANNEL_IN_USE),
                      f"channel {channel} is already connected")
