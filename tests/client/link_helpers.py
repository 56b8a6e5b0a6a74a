"""Bounded waits shared by the reconnect and fault tests (imported as ``link_helpers``)."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import time
from collections.abc import Callable
from typing import Any

import pytest

from waiting import poll_until, wait_until

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


def read_all(inbox: Any, n: int) -> list[Any]:
    """The first ``n`` values of ``inbox`` (a blocking channel), waiting as long as they keep
    coming within ``waiting.WAIT``; the failure says how many came."""
    got: list[Any] = []

    def all_came() -> bool:
        got.extend(inbox.read_many())
        return len(got) >= n

    wait_until(all_came, lambda: f"{n} values on {inbox.topic} ({len(got)} came)")
    return got


def time_while_frozen(proc: subprocess.Popen[str], caplog: pytest.LogCaptureFixture,
                      close: Callable[[], object],
                      then: Callable[[], object] = lambda: None) -> float:
    """Stop the server process (its sockets stay open, nobody answers), run ``then``, and
    time ``close`` with the SDK's warnings captured. The server runs again afterwards."""
    os.kill(proc.pid, signal.SIGSTOP)
    try:
        then()
        with caplog.at_level(logging.WARNING, logger="rlbridge.client"):
            started = time.monotonic()
            close()
            return time.monotonic() - started
    finally:
        os.kill(proc.pid, signal.SIGCONT)
