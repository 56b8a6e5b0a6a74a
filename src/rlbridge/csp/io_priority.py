"""The SDK's I/O threads at a real-time priority below the control loop (opt-in).

Why a separate piece: the priority is a property of the bridge, not of one session, so it
must be applied again to the threads every reconnect starts; keeping the request, the refusal
and the re-application together is what makes that one line in the reconnect path.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Callable, Iterable

from rlbridge.errors import RealTimeWarning

__all__ = ["IoPriority"]

ThreadIds = Callable[[], Iterable[int | None]]
"""The OS ids of the threads to place, read when placing (they change with a reconnect)."""


class IoPriority:
    """Remembers the asked ``SCHED_FIFO`` priority and places the threads ``ids`` names."""

    def __init__(self, ids: ThreadIds) -> None:
        self._ids = ids
        self.priority: int | None = None

    def request(self, priority: int) -> bool:
        """Place the threads now; ``False`` and one ``RealTimeWarning`` when refused."""
        try:
            self._place(priority)
        except (OSError, AttributeError) as exc:
            warnings.warn(RealTimeWarning(
                f"SDK threads stay at normal priority: SCHED_FIFO {priority} refused ({exc}); "
                "it needs CAP_SYS_NICE or RLIMIT_RTPRIO"), stacklevel=3)
            return False
        self.priority = priority
        return True

    def reapply(self) -> None:
        """After a reconnect: place the new session's threads like the old ones (best effort)."""
        if self.priority is not None:
            # granted before: a refusal now is a changed limit, and the link matters more
            with contextlib.suppress(OSError):
                self._place(self.priority)

    def _place(self, priority: int) -> None:
        for tid in self._ids():
            if tid is not None:
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
