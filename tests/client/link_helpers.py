"""Bounded waits shared by the reconnect and fault tests (imported as ``link_helpers``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

WAIT = 20.0


def wait_for(predicate: Callable[[], object], what: str, timeout: float = WAIT) -> None:
    """Poll ``predicate`` until it is true; fail after ``timeout`` naming ``what``."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.01)


def roundtrip(out: Any, inbox: Any, value: float) -> bool:
    """Write ``value`` until it arrives in ``inbox`` (a blocking channel).

    Writing again covers a value sent before the peer's binding existed (after a reconnect the
    two ends bind again in any order); bounded by ``WAIT``.
    """
    deadline = time.monotonic() + WAIT
    while time.monotonic() < deadline:
        out.write(value)
        try:
            while True:
                if inbox.read(timeout=0.2) == value:
                    return True
        except TimeoutError:
            continue
    return False
