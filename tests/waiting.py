"""The one way a test waits for something that happens in another thread or process.

Tests never assert a timing margin (docs: CONTRIBUTING, the quality bar): they wait, bounded by
a generous deadline, for the mechanism to show, and fail with what they waited for. Prefer an
event where the code under test offers one; poll with :func:`wait_until` where it does not.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

#: Generous bound for any single wait on a loaded 2-core machine; tests finish far sooner.
WAIT = 10.0


def wait_until(predicate: Callable[[], object], what: str = "condition", *,
               timeout: float = WAIT, interval: float = 0.01,
               between: Callable[[], object] | None = None) -> Any:
    """Poll ``predicate`` until it returns something truthy, and return that; fail (an
    ``AssertionError`` naming ``what``) after ``timeout`` seconds.

    ``between`` runs after every false answer, before the pause: what must be repeated for
    the condition to come (publish a value again: UDP may drop one).
    """
    deadline = time.monotonic() + timeout
    while True:
        result = predicate()
        if result:
            return result
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        if between is not None:
            between()
        time.sleep(interval)
