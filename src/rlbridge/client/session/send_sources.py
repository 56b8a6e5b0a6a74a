"""What the send thread needs of the channels it sends for (structural types).

The send thread (:mod:`rlbridge.client.session.sender`) takes values from outgoing channels and
grants
credit for flow-controlled incoming ones; these protocols say what it calls, so tests can hand
it sources of their own. An :class:`~rlbridge.client.channels.outgoing.OutgoingChannel` whose
``plain`` is
true is taken by :func:`~rlbridge.client.session.plain_round.take_plain` instead of ``take``.
"""

from __future__ import annotations

from typing import Protocol

from rlbridge.client.channels.pacing import Pacing


class OutgoingSource(Protocol):
    """What the send thread needs from an outgoing channel."""

    channel_id: int
    transport: str
    immediate: bool
    latest: bool
    pacing: Pacing | None
    #: The last take left values behind for the rate limit or credit: take again later.
    deferred: bool

    def take(self, congested: bool = False) -> tuple[int, list[int], list[object], int]:
        """What to send: ``(first_seq, stamps, values, repeated)``; empty lists when nothing.

        ``repeated`` leading values are redundant copies of values sent before.
        """
        ...

    @property
    def holding(self) -> bool:
        """A latest value is held back until the connection drains."""
        ...

    def pending(self) -> int:
        """How many values wait (for monitors)."""
        ...

    def ready(self, now_ns: int) -> bool:
        """Values wait and their credit and rate limit let one go now (wake-up predicate)."""
        ...

    def retry_in(self, now_ns: int) -> float | None:
        """Seconds until the rate limit lets a waiting value go; None: nothing to wait for."""
        ...

    def refused(self, count: int) -> None:
        """Receive thread: the server refused ``count`` values of this channel."""
        ...

    def left_out(self, count: int) -> None:
        """Send thread: ``count`` values too large to send (over the server's ``max_packet``,
        or a datagram) were not sent. Two methods, two counters: one writer each."""
        ...


class CreditSource(Protocol):
    """What the send thread needs from a flow-controlled incoming channel."""

    channel_id: int
    credited: int

    def credit_due(self) -> bool: ...

    def credit_limit(self) -> int: ...
