"""The one way a test waits for something that happens in another thread or process.

Tests never assert a timing margin (docs: CONTRIBUTING, the quality bar): they wait, bounded by
a generous deadline, for the mechanism to show, and fail with what they waited for. Prefer an
event where the code under test offers one; poll with :func:`wait_until` where it does not, with
:func:`wait_until_ok` where the sign is a call that stops failing (a server that accepts), and
with :func:`poll_until` where the caller decides what a timeout means.
``tests/architecture/test_wait_loops.py`` keeps hand-written deadline loops out of the tests.
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")

#: Generous bound for any single wait on a loaded 2-core machine; tests finish far sooner.
WAIT = 10.0


def wait_until(predicate: Callable[[], object], what: str | Callable[[], str] = "condition", *,
               timeout: float = WAIT, interval: float = 0.01,
               between: Callable[[], object] | None = None) -> Any:
    """Poll ``predicate`` until it returns something truthy, and return that; fail (an
    ``AssertionError`` naming ``what``) after ``timeout`` seconds.

    ``what`` may be a callable: it is asked at the timeout, so the failure can say how far the
    wait got (``lambda: f"{n} values ({len(got)} came)"``). ``between`` runs after every false
    answer, before the pause: what must be repeated for the condition to come (publish a value
    again: UDP may drop one). A predicate that blocks by itself (a read with a timeout) takes
    ``interval=0``.
    """
    result = poll_until(predicate, timeout=timeout, interval=interval, between=between)
    if not result:
        described = what() if callable(what) else what
        raise AssertionError(f"timed out after {timeout} s waiting for {described}")
    return result


def poll_until(predicate: Callable[[], object], *, timeout: float = WAIT,
               interval: float = 0.01, between: Callable[[], object] | None = None) -> Any:
    """:func:`wait_until` without the failure: the predicate's first truthy answer, or its
    last (falsy) one once ``timeout`` passed.

    For a caller that says itself what a timeout means: it tries again (flood once more), or
    answers a question (``roundtrip`` returns whether a value came through, and its callers
    assert with their own message).
    """
    deadline = time.monotonic() + timeout
    while True:
        result = predicate()
        if result or time.monotonic() >= deadline:
            return result
        if between is not None:
            between()
        time.sleep(interval)


def wait_until_ok(call: Callable[[], T], what: str, *,
                  errors: tuple[type[Exception], ...] = (Exception,), timeout: float = WAIT,
                  interval: float = 0.05, between: Callable[[], object] | None = None) -> T:
    """Call ``call`` until it returns instead of raising one of ``errors``, and return what it
    returned; fail after ``timeout`` seconds naming ``what`` and the last error.

    For a sign that is an attempt: a session opens once a server process serves. ``between``
    runs after every failed attempt (assert there that the server process still runs, so a
    crash fails at once with its own message).
    """
    last: list[Exception] = []

    def attempt() -> tuple[T] | None:
        try:
            return (call(),)  # in a tuple: a result that is falsy (None) is still a success
        except errors as exc:
            last[:] = [exc]
            return None

    def described() -> str:
        return f"{what} (the last attempt said: {last[-1]!r})" if last else what

    done: tuple[T] = wait_until(attempt, described, timeout=timeout, interval=interval,
                                between=between)
    return done[0]


def assert_running(proc: subprocess.Popen[Any]) -> None:
    """Fail at once, with the process's exit code and stderr, when ``proc`` has exited: the
    ``between`` of a wait for a process to serve (a crash says why, not "timed out")."""
    if proc.poll() is not None:
        _out, err = proc.communicate(timeout=WAIT)
        said = f": {err[-2000:]}" if err else ""
        raise AssertionError(f"{proc.args!r} exited with {proc.returncode}{said}")
