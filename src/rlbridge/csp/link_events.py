"""Link state for control code: a property, callbacks, and FIFO channels of events.

Control code must learn that the link went down without ever blocking on it. Three ways, all
fed from one place (:class:`LinkEvents`, owned by the :class:`~rlbridge.csp.bridge.Bridge`):

* ``bridge.link_state``: one attribute read, for a loop that branches every cycle;
* ``bridge.on_link_change(callback)``: called in the SDK thread that saw the change;
* ``bridge.link_events()``: a FIFO of :class:`LinkEvent` values (a buffered, blocking
  :class:`~rlbridge.csp.channel.Channel`): each event is read once, in order. ``try_read()``
  raises :class:`~rlbridge.errors.WouldBlock` when nothing new is there (events are not
  state: a drain loop ends), ``read(timeout)`` waits for the next one, ``read_many()`` takes
  every event not read yet. Overflow drops the oldest, counted in ``statistics()``. The
  current state is always ``bridge.link_state``.

Events come from the receive thread (watchdog, hang-up), the reconnect supervisor (bound
again) and the closing thread. Each channel is one-to-one, so the writers take one lock here;
readers take none. Fail-safes read :attr:`LinkEvents.lost`, a plain attribute.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from rlbridge.csp.channel import Channel
from rlbridge.wire.link import LinkState

#: Events each ``link_events()`` channel keeps for a reader that does not keep up.
DEFAULT_EVENT_BUFFER = 64


@dataclass(frozen=True, slots=True)
class LinkEvent:
    """The link changed to ``state`` at ``at_ns`` (``time.monotonic_ns``), and why.

    A loss event (``channel >= 0``) leaves the state as it is: the server reported that
    ``lost`` values of publish channel ``channel`` never arrived at the first hop since
    its previous report (docs/policies.md, loss feedback).
    """

    state: LinkState
    at_ns: int
    reason: str
    channel: int = -1
    lost: int = 0


class LinkEvents:
    """Fans every link change out to callbacks and event channels, in order."""

    def __init__(self, state: LinkState = LinkState.CONNECTED) -> None:
        self._lock = threading.RLock()  # a callback may subscribe another channel
        self._last = LinkEvent(state, time.monotonic_ns(), "initial state")
        self._callbacks: list[Callable[[LinkState], None]] = []
        self._channels: list[Channel[LinkEvent]] = []
        #: True while the link is lost; read lock-free by fail-safes on every channel read.
        self.lost = state is LinkState.LOST

    @property
    def last(self) -> LinkEvent:
        return self._last

    def add_callback(self, callback: Callable[[LinkState], None]) -> None:
        with self._lock:
            self._callbacks.append(callback)

    def channel(self, buffer_size: int = DEFAULT_EVENT_BUFFER) -> Channel[LinkEvent]:
        """A new FIFO whose first event is the current state, then every change."""
        with self._lock:
            ch: Channel[LinkEvent] = Channel(buffer_size, blocking=True, name="link events")
            ch.write(self._last)
            self._channels.append(ch)
            return ch

    def emit(self, state: LinkState, reason: str) -> None:
        """Record a change (repeats of the current state are ignored)."""
        with self._lock:
            if state is self._last.state:
                return
            event = self._last = LinkEvent(state, time.monotonic_ns(), reason)
            self.lost = state is LinkState.LOST
            self._channels = [ch for ch in self._channels if not ch.closed]
            for ch in self._channels:
                ch.write(event)
            for callback in self._callbacks:
                callback(state)

    def emit_loss(self, channel: int, lost: int, reason: str) -> None:
        """Record first-hop loss of a publish channel: an event in every channel, the state
        unchanged (callbacks, which follow state changes, are not called)."""
        with self._lock:
            event = LinkEvent(self._last.state, time.monotonic_ns(), reason, channel, lost)
            self._channels = [ch for ch in self._channels if not ch.closed]
            for ch in self._channels:
                ch.write(event)

    def close(self) -> None:
        """Close every event channel (their buffered events stay readable)."""
        with self._lock:
            for ch in self._channels:
                ch.close()
            self._channels = []
