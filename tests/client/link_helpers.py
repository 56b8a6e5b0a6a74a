"""Bounded waits shared by the reconnect and fault tests (imported as ``link_helpers``)."""

from __future__ import annotations

from typing import Any

from waiting import poll_until

#: A reconnect takes a watchdog timeout, a back-off and a handshake: more than waiting.WAIT.
WAIT = 20.0


def roundtrip(out: Any, inbox: Any, value: float) -> bool:
    """Write ``value`` until it arrives in ``inbox`` (a blocking channel); whether it did
    within ``WAIT`` (callers assert with their own message).

    Writing again covers a value sent before the peer's binding existed (after a reconnect the
    two ends bind again in any order).
    """
    def arrived() -> bool:
        out.write(value)
        try:
            while True:  # older values first; the read blocks 0.2 s at most
                if inbox.read(timeout=0.2) == value:
                    return True
        except TimeoutError:
            return False

    return bool(poll_until(arrived, timeout=WAIT, interval=0))
