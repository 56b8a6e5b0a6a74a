"""The GIL switch interval an HRT loop runs with (measured in docs/gil.md).

A loop thread that wakes while another thread of its interpreter runs Python code waits for
the GIL until that thread blocks, or at most one *switch interval* (``sys.getswitchinterval()``,
5 ms by default) before CPython forces a hand-over. The SDK's own threads block in C almost
all the time and are not what this protects against (a shorter interval did not change their
cost to the loop by much); a *computing* Python thread next to the loop is: with 5 ms it skipped
two thirds of a 1 kHz loop's releases.

The setting is process-wide, so it belongs to whoever runs an HRT loop, for as long as the loop
runs: :class:`~rlbridge.hrt.coupling.ControlLoop` holds :func:`shorter_switch_interval` while it
runs (``Bridge.connect`` leaves the interpreter alone by default). Holders nest and overlap:
the shortest asked for applies while any holds it, and the value from before the first comes
back when the last ends, unless somebody else changed it meanwhile (then theirs stays).
"""

from __future__ import annotations

import contextlib
import sys
import threading
from collections.abc import Iterator
from typing import Final

__all__ = ["HRT_SWITCH_INTERVAL", "realtime_switch_interval", "shorter_switch_interval"]

HRT_SWITCH_INTERVAL: Final = 0.0001
"""What an HRT loop runs with: a computing thread delays the loop by at most about 0.1 ms.

Measured next to a 1 kHz loop (docs/gil.md, 10 rounds): a pure-Python thread moved the loop's
median lateness by +645 us at CPython's 5 ms, +536 us at 0.5 ms and +167 us at 0.1 ms; the
SDK's own threads at 1 kHz cost +531, +390 and +353 us at p99. What CPU-bound threads pay for
the extra forced hand-overs was within this machine's noise.
"""


class _Holders:
    """Who currently wants a short interval, and what to restore after the last of them."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.count = 0
        self.saved = 0.0  # the interval before the first holder
        self.installed: float | None = None  # what the holders set (None: nothing changed)


_holders = _Holders()


@contextlib.contextmanager
def shorter_switch_interval(seconds: float | None = HRT_SWITCH_INTERVAL) -> Iterator[None]:
    """Run the block with a switch interval of at most ``seconds`` (``None``: leave it)."""
    if seconds is None:
        yield
        return
    if seconds <= 0:
        raise ValueError(f"switch interval must be positive, got {seconds}")
    h = _holders
    with h.lock:
        if h.count == 0:
            h.saved, h.installed = sys.getswitchinterval(), None
        h.count += 1
        if sys.getswitchinterval() > seconds:
            sys.setswitchinterval(seconds)
            h.installed = sys.getswitchinterval()
    try:
        yield
    finally:
        with h.lock:
            h.count -= 1
            if h.count == 0 and h.installed is not None \
                    and sys.getswitchinterval() == h.installed:
                sys.setswitchinterval(h.saved)


def realtime_switch_interval(seconds: float = HRT_SWITCH_INTERVAL) -> float:
    """Set the process's switch interval for good (no loop owns it); return the previous one.

    For a program that runs its HRT loop outside a :class:`~rlbridge.hrt.coupling.Coupling`.
    """
    if seconds <= 0:
        raise ValueError(f"switch interval must be positive, got {seconds}")
    previous = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    return previous
