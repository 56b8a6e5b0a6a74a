"""Turn SIGTERM into an exception for a bounded stretch of code, so ``with`` blocks unwind.

By default SIGTERM ends a Python process without running ``finally`` blocks or context
manager exits, which would leave namespaces behind.  :func:`sigterm_raises` installs a
handler that raises :class:`Terminated` (a ``SystemExit``) in the main thread and puts the
previous handler back afterwards.  It changes nothing when called from another thread
(signal handlers belong to the main thread) or when someone else already handles SIGTERM.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

SIGTERM_EXIT_CODE = 128 + signal.SIGTERM


class Terminated(SystemExit):
    """Raised in the main thread when SIGTERM arrives inside :func:`sigterm_raises`."""


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    raise Terminated(SIGTERM_EXIT_CODE)


@contextmanager
def sigterm_raises() -> Iterator[bool]:
    """Within the block SIGTERM raises :class:`Terminated`; yields whether it was installed."""
    installable = (
        threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    )
    if not installable:
        yield False
        return
    signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield True
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
