"""End-to-end flow control for channels that promise every value (TCP, not ``latest``).

Theory of operation (credit, as in HTTP/2 and QUIC streams, counted in values). A value is
never dropped for being early; it waits where control code can see it.

* **Subscriber -> server.** A subscribe channel bound with ``flow`` tells the server how many
  values it may have in flight: ``buffer_size`` at first, then ``Credit(channel, limit)``
  packets as the reader consumes (the client's ring never overflows). The server's
  :class:`OutboundCredit` sends the values numbered below ``limit`` and keeps the rest in a
  backlog, in order.
* **Server -> publisher.** A publish channel bound with ``flow`` may send the values numbered
  below the limit the server grants (``TopicAck.credit``, then ``Credit`` packets). The
  server's :class:`InboundCredit` grants what the *slowest* flow-controlled subscriber of the
  topic on this server has room for in its backlog (at most :data:`CREDIT_CHUNK` ahead), so
  once a subscriber stops reading, its backlog fills, the publishers' credit runs out, and
  the values wait in the publisher's ring, where its overflow policy applies and is counted.

The two halves meet in a :class:`TopicFlow` per topic (:class:`FlowTable` owns them, one per
server): a backlog that drains re-grants credit to every publisher of the topic. Values that
reach a backlog beyond :data:`BACKLOG_HARD` (a publisher outside the bridge, or one that
ignores credit) are dropped and counted in the channel's ``dropped``, as before.

``latest`` channels keep their own policy (hold the newest, drop the rest at the server) and
UDP channels have no flow control: their first-hop loss is reported instead (``LossReport``).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

from rlbridge.wire import Credit, TopicConnect

#: Bytes queued for the client (transport buffer and corked frames) past which a
#: flow-controlled channel stops sending and keeps values in its backlog, as a fraction of
#: the server's ``max_write_buffer`` (where other channels start dropping).
SOCKET_SHARE = 2

#: Most credit a publisher is granted ahead of what arrived (values).
CREDIT_CHUNK = 1 << 16
#: A subscriber's backlog that stops new credit to the topic's publishers (values).
BACKLOG_SOFT = 1 << 16
#: A backlog this long drops (and counts) what still arrives: nothing may grow unbounded.
BACKLOG_HARD = 8 * BACKLOG_SOFT


def wants_flow(req: TopicConnect) -> bool:
    """True for a channel under credit flow control: asked for, TCP, and not ``latest``."""
    return req.flow and req.transport == "tcp" and not req.latest


class OutboundCredit:
    """Server -> subscriber half: sends within the subscriber's credit, backlogs the rest.

    It also keeps values back while the client's TCP connection has ``max_queued`` bytes
    waiting (``queued()``): a channel that promises every value waits for the socket too,
    where other channels would have their values dropped at ``max_write_buffer``.
    """

    def __init__(self, window: int, flow: TopicFlow, queued: Callable[[], int] = lambda: 0,
                 max_queued: int = 1 << 62) -> None:
        #: Values numbered below this may be sent (initially the client's ring size).
        self.limit = max(1, window)
        #: Waiting values in the batches they came in, ``(stamp, values)``: per batch, not
        #: per value, so a backlog costs list slices, not a tuple per value.
        self._chunks: deque[tuple[int, list[Any]]] = deque()
        #: Values in the backlog.
        self.waiting = 0
        self.flow = flow
        self._queued = queued
        self._max_queued = max_queued
        #: The last take stopped because the socket had too much queued: try again later.
        self.socket_full = False

    def room(self) -> int:
        """Values the backlog takes before publishers stop getting credit."""
        return max(0, BACKLOG_SOFT - self.waiting)

    def queue(self, stamp: int, values: Sequence[Any]) -> int:
        """Add values behind the backlog; returns how many did not fit (dropped)."""
        fit = max(0, min(len(values), BACKLOG_HARD - self.waiting))
        if fit:
            self._chunks.append((stamp, list(values[:fit])))
            self.waiting += fit
        return len(values) - fit

    def take(self, next_seq: int, most: int) -> tuple[list[int], list[Any]]:
        """What may go now (at most ``most``), given the next sequence number to send."""
        n = min(self.waiting, self.limit - next_seq, most)
        if n <= 0:
            return [], []
        self.socket_full = self._queued() > self._max_queued
        if self.socket_full:
            return [], []
        stamps: list[int] = []
        values: list[Any] = []
        chunks = self._chunks
        left = n
        while left:
            stamp, chunk = chunks[0]
            if len(chunk) <= left:
                chunks.popleft()
                part = chunk
            else:
                part, chunks[0] = chunk[:left], (stamp, chunk[left:])
            values += part
            stamps += [stamp] * len(part)
            left -= len(part)
        self.waiting -= n
        if self.waiting < BACKLOG_SOFT:
            self.flow.changed()
        return stamps, values

    def clear(self) -> int:
        """Drop the backlog (the channel closes); returns how many values it held."""
        dropped, self.waiting = self.waiting, 0
        self._chunks.clear()
        return dropped

    def on_credit(self, limit: int) -> bool:
        """A credit arrived; True if it moved the limit (then values may go)."""
        if limit <= self.limit:
            return False
        self.limit = limit
        return True


class InboundCredit:
    """Server -> publisher half: how far the publisher may send; grants as room appears."""

    def __init__(self, channel: int, flow: TopicFlow,
                 send: Callable[[Credit], None]) -> None:
        self.channel = channel
        self.flow = flow
        self._send = send
        self.granted = 0
        self.credits_sent = 0

    def first(self, next_seq: int) -> int:
        """The credit of the binding's ``TopicAck`` (the publisher numbers from 0)."""
        self.granted = next_seq + min(self.flow.room(), CREDIT_CHUNK)
        return self.granted

    def grant(self, next_seq: int) -> None:
        """Send a new credit if room moved it by a quarter chunk (or the publisher waits)."""
        limit = next_seq + min(self.flow.room(), CREDIT_CHUNK)
        step = limit - self.granted
        if step <= 0:
            return
        if step >= CREDIT_CHUNK // 4 or next_seq >= self.granted:
            self.granted = limit
            self.credits_sent += 1
            self._send(Credit(self.channel, limit))


class TopicFlow:
    """The flow-controlled bindings of one topic on this server."""

    def __init__(self) -> None:
        self.outbound: set[OutboundCredit] = set()
        #: Each publisher's credit and a callable giving its next expected sequence number.
        self.inbound: dict[InboundCredit, Callable[[], int]] = {}
        self._granting = False

    def room(self) -> int:
        """The smallest backlog room among the subscribers (a full chunk with none)."""
        return min((o.room() for o in self.outbound), default=CREDIT_CHUNK)

    def changed(self) -> None:
        """A backlog drained: publishers may get credit again."""
        if self._granting:  # a grant that sends may not re-enter through a drain
            return
        self._granting = True
        try:
            for credit, next_seq in list(self.inbound.items()):
                credit.grant(next_seq())
        finally:
            self._granting = False

    @property
    def empty(self) -> bool:
        return not (self.outbound or self.inbound)


class FlowTable:
    """Topic name -> :class:`TopicFlow`, one table per server (in its ServerContext)."""

    def __init__(self) -> None:
        self._topics: dict[str, TopicFlow] = {}

    def topic(self, name: str) -> TopicFlow:
        flow = self._topics.get(name)
        if flow is None:
            flow = self._topics[name] = TopicFlow()
        return flow

    def release(self, name: str) -> None:
        """Forget a topic's entry once no flow-controlled binding uses it."""
        flow = self._topics.get(name)
        if flow is not None and flow.empty:
            del self._topics[name]
