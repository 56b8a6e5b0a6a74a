"""What a :class:`~rlbridge.csp.bridge.Bridge` tells about its session: link, state, counters.

Read-only views for control code and monitors, split from the Bridge so that its module
keeps to opening sessions and channels. Every property here is one attribute read or a
snapshot: none blocks, except :meth:`BridgeStatus.server_stats`, which asks the server.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rlbridge.csp.channel import Channel
from rlbridge.csp.connection import Connection
from rlbridge.csp.link_events import DEFAULT_EVENT_BUFFER, LinkEvent, LinkEvents
from rlbridge.csp.reconnect import ClientState, ReconnectSupervisor
from rlbridge.wire.link import LinkState


class BridgeStatus:
    """The Bridge's link state, session facts and counters (a base class of ``Bridge``)."""

    _conn: Connection
    _events: LinkEvents
    _supervisor: ReconnectSupervisor | None

    @property
    def link_state(self) -> LinkState:
        """``connected``, ``degraded`` or ``lost``: read it from control code, it never blocks.

        ``lost`` from the end of a session until its channels are bound again. The same
        source as the fail-safes and the link events: once this says ``lost``, they have
        engaged and the event is in every ``link_events()`` channel.
        """
        return self._events.last.state

    @property
    def state(self) -> ClientState:
        """``connected``, ``reconnecting`` or ``closed`` (for good)."""
        return self._conn.state

    @property
    def closed(self) -> bool:
        """True once the bridge is closed for good: here, or its session ended without reconnect."""
        return self._conn.closed.is_set()

    @property
    def close_reason(self) -> str:
        """Why the last session ended (``""`` while the first one is open)."""
        return self._conn.close_reason

    @property
    def reconnects(self) -> int:
        """Sessions opened again after one ended (0 with ``reconnect=False``)."""
        return 0 if self._supervisor is None else self._supervisor.reconnects

    def on_link_change(self, callback: Callable[[LinkState], None]) -> None:
        """Call ``callback(state)`` in the SDK thread that saw the change; keep it short."""
        self._events.add_callback(callback)

    def link_events(self, buffer_size: int = DEFAULT_EVENT_BUFFER) -> Channel[LinkEvent]:
        """A FIFO of :class:`LinkEvent` values: every link change (and first-hop loss report),
        each read once, in order.

        Its first event is the current state. ``try_read()`` raises :class:`WouldBlock` when
        nothing new is there, ``read(timeout)`` waits for the next event, ``read_many()``
        takes every event not read yet (``[]`` when none). Events are not state: the state now
        is :attr:`link_state`. A reader that falls ``buffer_size`` events behind loses the
        oldest (``statistics().overwritten``). Closed with the bridge (events still buffered
        stay readable, then ``ChannelClosed``).
        """
        return self._events.channel(buffer_size)

    @property
    def rtt_ns(self) -> int:
        """Smoothed round-trip time from heartbeats (-1 until measured)."""
        link = self._conn.link
        return -1 if link is None else link.stats(0).rtt_ns

    @property
    def local_ports(self) -> dict[str, int]:
        """The current session's local TCP and UDP ports (they change with every reconnect)."""
        return self._conn.local_ports()

    def server_stats(self) -> dict[str, Any]:
        """The server's counters for this session, its totals, and the topics it knows."""
        return dict(self._conn.request_stats())

    @property
    def session_id(self) -> int:
        """The number the server gave this session: it names it in logs and ``rlbridge stats``."""
        assert self._conn.ack is not None
        return self._conn.ack.session

