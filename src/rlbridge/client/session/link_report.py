"""What one connection tells its owner about the link: in order, and final at a session's end.

Three threads report the link: the receive thread (its watchdog: ``degraded``, ``connected``),
whoever ends a session (``lost``) and the reconnect supervisor once a new session's channels
are bound again. Without an order between them a session's last packets, a goodbye say, could
report ``connected`` after its end reported ``lost``, and fail-safes would disengage while no
session is up. So every report takes one lock, and a session's end closes that session for
reports: the receive thread of an ended session can no longer say anything.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from rlbridge.wire.link import LinkState

#: ``(state, reason)``: the owner's handler (the Bridge's link events).
LinkHandler = Callable[[LinkState, str], None]


class LinkReport:
    """The current session's link state and the one place that tells it."""

    def __init__(self) -> None:
        #: The link state of the current session (what ``on_change`` was last told, unless
        #: the session is still being bound again: see :meth:`restored`).
        self.state = LinkState.CONNECTED
        self.on_change: LinkHandler | None = None
        self._lock = threading.RLock()  # a handler may close the bridge, which reports again
        self._session = 0  # the generation whose reports count; 0 while none is up
        self._told = True

    def session_started(self, generation: int, *, told: bool) -> None:
        """Session ``generation`` is up. ``told=False`` keeps the owner's view ``lost`` until
        :meth:`restored` (a reconnect: its channels are not bound again yet)."""
        with self._lock:
            self._session, self._told = generation, told
            self.state = LinkState.CONNECTED

    def update(self, state: LinkState, reason: str, generation: int) -> None:
        """The receive thread of session ``generation`` saw the link change; ignored once
        that session has ended."""
        with self._lock:
            if generation != self._session:
                return
            self.state = state
            if self._told and self.on_change is not None:
                self.on_change(state, reason)

    def restored(self, reason: str) -> None:
        """The owner has bound the new session's channels again: tell its link state."""
        with self._lock:
            if not self._session or self._told:
                return
            self._told = True
            if self.on_change is not None:
                self.on_change(self.state, reason)

    def session_ended(self, reason: str) -> None:
        """The session is over: ``lost``, and nothing it still reads may say otherwise."""
        with self._lock:
            self._session = 0
            self.state = LinkState.LOST
            if self.on_change is not None:
                self.on_change(LinkState.LOST, reason)
