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

Cost. Credit moves in quarter chunks, so nothing here needs to run per value: an arriving
packet costs :meth:`InboundCredit.grant` one comparison until the publisher's sequence number
reaches the first point where a grant could be due (``check_at``), and a drained backlog only
marks its topic; the topic re-grants once, at the end of the event-loop iteration (the
running loop's ``call_soon``), whatever that iteration drained; and a value that finds its
subscriber's backlog empty, the credit and the socket free, passes the backlog
(:meth:`OutboundCredit.passes`). With one value per TCP frame this took the server's
flow-control work from about half of its time per value to a few percent.
"""

from __future__ import annotations

import asyncio
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
        #: Values numbered below this may be sent: initially the room in the client's ring
        #: (its size; after a reconnect, what unread values leave free: 0 waits for a Credit).
        self.limit = max(0, window)
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
        n = len(values)
        if 0 < n <= BACKLOG_HARD - self.waiting:  # the common case: all of them
            self._chunks.append((stamp, list(values)))
            self.waiting += n
            return 0
        fit = max(0, min(n, BACKLOG_HARD - self.waiting))
        if fit:
            self._chunks.append((stamp, list(values[:fit])))
            self.waiting += fit
        return len(values) - fit

    def passes(self, next_seq: int, n: int) -> bool:
        """``n`` new values may go at once, past the backlog: none waits, the credit covers
        them and the socket has room (what ``queue`` then ``take`` would allow, without
        either: one value per frame costs no backlog entry)."""
        return (not self.waiting and next_seq + n <= self.limit
                and self._queued() <= self._max_queued)

    def take(self, next_seq: int, most: int) -> tuple[list[int], list[Any]]:
        """What may go now (at most ``most``), given the next sequence number to send."""
        n = min(self.waiting, self.limit - next_seq, most)
        if n <= 0:
            return [], []
        self.socket_full = self._queued() > self._max_queued
        if self.socket_full:
            return [], []
        chunks = self._chunks
        stamp, chunk = chunks[0]
        if len(chunk) == n:  # the common case (one value in, one out): the batch as it came
            chunks.popleft()
            self.waiting -= n
            if self.waiting < BACKLOG_SOFT:
                self.flow.changed()
            return [stamp] * n, chunk
        stamps: list[int] = []
        values: list[Any] = []
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
        #: The publisher's next sequence number from which an arrival can make a grant due
        #: with the room there was at the last look (:meth:`grant`). Room only shrinks until
        #: a backlog drains, and a drain re-grants through :meth:`regrant`.
        self.check_at = 0

    def first(self, next_seq: int) -> int:
        """The credit of the binding's ``TopicAck`` (the publisher numbers from 0)."""
        room = min(self.flow.room(), CREDIT_CHUNK)
        self.granted = next_seq + room
        self._next_check(room)
        return self.granted

    def grant(self, next_seq: int) -> None:
        """Values arrived: send a new credit if room moved it by a quarter chunk (or the
        publisher waits). Per packet this is one comparison: before ``check_at`` no grant
        can be due, whatever the room (module docstring)."""
        if next_seq >= self.check_at:
            self.regrant(next_seq)

    def regrant(self, next_seq: int) -> None:
        """:meth:`grant` without the shortcut: room may have grown (a backlog drained)."""
        room = min(self.flow.room(), CREDIT_CHUNK)
        limit = next_seq + room
        step = limit - self.granted
        if step > 0 and (step >= CREDIT_CHUNK // 4 or next_seq >= self.granted):
            self.granted = limit
            self.credits_sent += 1
            self._send(Credit(self.channel, limit))
        self._next_check(room)

    def _next_check(self, room: int) -> None:
        """The first sequence number at which ``regrant`` could grant with ``room`` or less:
        where the step reaches a quarter chunk, or where the publisher has used it all."""
        self.check_at = min(self.granted, self.granted + CREDIT_CHUNK // 4 - room)


class TopicFlow:
    """The flow-controlled bindings of one topic on this server."""

    def __init__(self) -> None:
        self.outbound: set[OutboundCredit] = set()
        #: Each publisher's credit and a callable giving its next expected sequence number.
        self.inbound: dict[InboundCredit, Callable[[], int]] = {}
        self._granting = False
        #: A re-grant is scheduled for the end of this event-loop iteration.
        self._due = False

    def room(self) -> int:
        """The smallest backlog room among the subscribers (a full chunk with none)."""
        return min((o.room() for o in self.outbound), default=CREDIT_CHUNK)

    def changed(self) -> None:
        """A backlog drained: publishers may get credit again, once this loop iteration is
        over (every drain of the iteration in one look); at once without a running loop."""
        if self._due or self._granting:  # a grant that sends may not re-enter through a drain
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # driven by hand (tests): grant now
            self.regrant()
            return
        self._due = True
        loop.call_soon(self.regrant)

    def regrant(self) -> None:
        """Give every publisher of the topic what the subscribers' room allows now."""
        self._due = False
        self._granting = True
        try:
            for credit, next_seq in list(self.inbound.items()):
                credit.regrant(next_seq())
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
