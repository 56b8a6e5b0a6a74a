"""The send thread: the code that writes values to the network (see *inline rounds* below).

Theory of operation. Control code writes into outgoing channels, which only store the value in
a ring buffer (no lock, no system call). This soft-real-time thread drains the rings and does
the I/O. It wakes for three reasons: an *immediate* channel was written, ``Bridge.send()``
asked to flush the shared buffer (thesis: ``send through buffer``), or the SDK's own send loop
ticks at its configured rate (thesis 4.3, figure 5.10). The first two ring its bell
(:mod:`rlbridge.csp.bell`) only while it is parked: one futex wake, no lock; ``send()`` counts
a request, and a round is due while the count differs from the one the last round saw.
Every value waiting in a channel goes out in one packet per channel (a Batch when there are
several; on TCP cut at ``max_batch`` values and at the server's ``max_packet`` bytes, since
one frame over that would end the session: :func:`~rlbridge.wire.codec.encode_run_into`,
which leaves out, says and counts a value alone over it); TCP frames of all channels are
coalesced into one ``sendall``, and the packets of all UDP channels into one datagram (a
``Bundle``, split only at ``DATAGRAM_BUDGET`` bytes; :mod:`rlbridge.wire.bundle`). So the
packet rate follows the send loop, not the control loop, and not the number of channels.

A round costs Python per channel, so the common case takes the short way: a *plain* UDP
channel (no policy between its ring and the wire: no rate limit, credit, latest, age limit or
redundancy) is taken by one inline loop (:func:`~rlbridge.client.session.plain_round.take_plain`) as
tuples shaped like ``Value`` packets, and the round's parts are encoded by one msgspec call
into one datagram (:meth:`~rlbridge.wire.bundle.DatagramPacker.send_parts`; a sealed session
seals that one encoding). Channels with policies, TCP channels, and rounds that cannot bundle
(``bundles=False``, a round larger than a datagram) go through ``take`` and the packer part by
part, as before.

While the link is down (:meth:`SendLoop.pause`, from the end of a session until its channels are
bound again) the thread takes nothing: values wait in their channels' rings, which keep the
newest (overflow counted in ``overwritten``), and go out on :meth:`SendLoop.resume`.

Channel policies (docs/policies.md) are applied in ``OutgoingChannel.take``: a *latest*
channel on TCP is handed the kernel's view of the connection (:mod:`rlbridge.tcpstate`) and,
while it is backed up, holds its newest value instead of queueing a burst behind a
retransmission; this thread then re-checks every ``HOLD_POLL_S`` until the value is out.
UDP channels with ``redundancy`` k carry the previous k values in each datagram. A channel's
:class:`~rlbridge.client.channels.pacing.Pacing` (credit of a flow-controlled TCP channel, a
``max_rate_hz`` limit) may let only part of what waits go; the rest stays in the ring, the
thread comes back when the rate allows (``retry_in``) or a ``Credit`` rings its doorbell. The
thread also grants credit for flow-controlled incoming channels whose reader consumed enough
(a ``Credit`` frame in the same ``sendall`` as the values).

How the thread waits for work is its :mod:`~rlbridge.csp.idle` strategy (park, spin then
park, busy spin): ``Bridge.connect(tuning=Tuning(idle=...))``.

**Inline rounds** (``Bridge.send(inline=True)``): a caller may run the round itself, in its
own thread, under the same round lock (:meth:`SendLoop.send_inline`).

Why. Waking the send thread costs the caller a futex wake and the thread its own wake-up
before its ``sendto``: a cross-thread hand-off on every value's path,
tens of microseconds on a VM. A caller that may make a network system call (SRT code, never an
HRT loop: docs/concepts.md, "Sending") can do the round itself: take the plain channels and
send their one datagram with a ``sendto`` that never waits (``MSG_DONTWAIT``).

When. The plain channels (UDP, no policy) go inline when the session bundles
(:attr:`DatagramPacker.one_call`) without a seal (the AEAD stays the send thread's) and the
link is up; otherwise the caller rings the send
thread exactly as ``send()`` does. Channels with a policy or on TCP stay the send thread's:
when one of them has something to send, the caller rings the thread for it after its own
datagram (so such a round leaves as two datagrams, not one). Credit for flow-controlled
incoming channels is the thread's business either way (their reader rings it). Never from a
process marked hard-real-time (:func:`~rlbridge.csp.process.current_process`): the rule that
HRT code makes no system call for the network holds there, with one ``RealTimeWarning``.

Safety. A round, wherever it runs, holds ``_round``: the send thread waits for it, the caller
only *tries* it. So two rounds never overlap, the channels' rings keep one reader at a time,
and no channel's values are reordered. A round the caller has taken but cannot send (larger
than one datagram, or ``EAGAIN``: the socket buffer is full) is *handed over*: the send thread
sends it first in its next round (:meth:`SendLoop._take_handoff`), before anything taken
later, so nothing is lost; a session that ended meanwhile takes it along, counted as a failed
round is.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
import warnings

from rlbridge.client.channels.outgoing import OutgoingChannel
from rlbridge.client.session.connection import Connection, ConnectionClosed
from rlbridge.client.session.plain_round import take_plain
from rlbridge.client.session.send_sources import CreditSource, OutgoingSource
from rlbridge.csp.bell import SendBell
from rlbridge.csp.idle import PARK, IdleStrategy, Park
from rlbridge.csp.process import current_process
from rlbridge.errors import RealTimeWarning
from rlbridge.tcpstate import congested
from rlbridge.wire import MAX_DATAGRAM, Batch, Credit, Error, ErrorCode, Value
from rlbridge.wire.bundle import DatagramPacker, Part, as_packet
from rlbridge.wire.codec import DEFAULT_MAX_PACKET, FLAG_BUNDLES, encode_run_into

log = logging.getLogger("rlbridge.client")

#: Largest datagram the send thread makes from a batch (fits a 1500-byte Ethernet MTU).
DATAGRAM_BUDGET = 1400
#: How often a held latest value re-checks whether the TCP connection has drained.
HOLD_POLL_S = 0.001

_DONTWAIT = socket.MSG_DONTWAIT


class SendLoop:
    """Owns the send thread (started by the Bridge, stopped and joined by ``close``) and the
    round lock under which a caller may run a round itself (``send_inline``)."""

    def __init__(self, conn: Connection, *, rate_hz: float | None, max_batch: int,
                 idle: IdleStrategy = PARK) -> None:
        if rate_hz is not None and rate_hz <= 0:
            raise ValueError(f"send loop rate must be positive, got {rate_hz}")
        self._conn = conn
        self.rate_hz = rate_hz
        self._period = 1.0 / rate_hz if rate_hz else None
        #: The values per Batch until a session's ack says (the server's ``max_batch``, read
        #: every round like its ``max_packet``: a reconnect may reach other limits).
        self._max_batch = max(1, max_batch)
        self._sources: tuple[OutgoingSource, ...] = ()
        #: Of ``_sources``: the plain ones (all; the immediate ones), and the others.
        self._plain: tuple[OutgoingChannel, ...] = ()
        self._plain_immediate: tuple[OutgoingChannel, ...] = ()
        self._others: tuple[OutgoingSource, ...] = ()
        #: The sources whose own state can wake this thread (immediate, or paced: deferred).
        self._wakers: tuple[OutgoingSource, ...] = ()
        #: A round's UDP parts, reused: one msgspec call encodes them all (wire/bundle.py).
        self._parts: list[Part] = []
        self._credits: tuple[CreditSource, ...] = ()
        self.idle = idle
        #: Seconds until a rate-limited value may go (None: no such value waits).
        self._retry: float | None = None
        #: Some channel's values still wait for credit or the rate limit (``flush(wait)``).
        self._deferred = False
        #: Rung by immediate channels' writes and ``flush``, only while this thread sleeps.
        self.doorbell = SendBell()
        #: ``flush`` calls so far, and the count the last completed round had seen: a round
        #: is due while they differ (two counters, so no flush is lost to a reset).
        self._flush_asked = 0
        self._flush_done = 0
        #: ``flush(wait=True)`` callers waiting on ``_flushed`` (the round notifies only then).
        self._flush_waiters = 0
        self._flushed = threading.Condition()
        self._stopping = False
        self._paused = False
        self._io_thread = threading.Thread(target=self._run, name="rlbridge-send", daemon=True)
        self.packets_sent = 0
        self.values_sent = 0
        self.values_repeated = 0
        self.send_errors = 0
        self._holding = False
        self._packer: DatagramPacker | None = None
        self.datagrams_sent = 0
        #: Rounds this thread ran (its wake-ups with work).
        self.rounds = 0
        #: Held by whoever runs a round: the send thread (waiting for it), or
        #: ``send_inline``'s caller (only if free).
        self._round = threading.Lock()
        #: Parts an inline round took but could not send, and the packer they were for.
        self._handoff: tuple[DatagramPacker, list[Part]] | None = None
        #: Rounds sent in a caller's thread; calls that rang the send thread instead, and of
        #: those the rounds handed over after the caller had taken them.
        self.inline_rounds = 0
        self.inline_fallbacks = 0
        self.inline_handoffs = 0
        self._hrt_warned = False
        conn.on_error = self._on_error

    def _on_error(self, error: Error) -> None:
        """Receive thread: an ``Error(BAD_VALUE)`` counts the values the server refused."""
        if error.code != ErrorCode.BAD_VALUE or error.channel is None:
            return
        for source in self._sources:
            if source.channel_id == error.channel:
                source.refused(error.values or 1)

    def start(self) -> None:
        self._io_thread.start()

    @property
    def native_id(self) -> int | None:
        """The send thread's OS id (for ``Bridge.set_io_priority``), ``None`` when not running."""
        return self._io_thread.native_id if self._io_thread.is_alive() else None

    def pause(self) -> None:
        """Keep values in their channels (the link is down); flushes return at once."""
        self._paused = True

    def resume(self) -> None:
        """Send again, starting with everything that waited (the channels are bound again)."""
        self._paused = False
        self.flush()

    def add(self, source: OutgoingSource) -> None:
        self._set_sources((*self._sources, source))

    def remove(self, source: OutgoingSource) -> None:
        self._set_sources(tuple(s for s in self._sources if s is not source))

    def _set_sources(self, sources: tuple[OutgoingSource, ...]) -> None:
        """Sort the sources once, not per round: plain ones take the short way."""
        plain = tuple(s for s in sources if isinstance(s, OutgoingChannel) and s.plain)
        self._plain = plain
        self._plain_immediate = tuple(s for s in plain if s.immediate)
        self._others = tuple(s for s in sources if s not in plain)
        self._wakers = tuple(s for s in sources if s.immediate or s.pacing is not None)
        self._sources = sources

    def add_credit(self, source: CreditSource) -> None:
        """A flow-controlled incoming channel: this thread grants the server its credit."""
        self._credits = (*self._credits, source)

    def remove_credit(self, source: CreditSource) -> None:
        self._credits = tuple(s for s in self._credits if s is not source)

    def flush(self, wait: bool = False, timeout: float = 5.0) -> None:
        """Send every buffered value now (``Bridge.send``); optionally wait until it is out.

        With ``wait``, also until no value waits for credit or a rate limit any more (at
        their pace, within ``timeout``). While paused the values stay buffered and this
        returns at once: they go on resume.
        """
        if self._paused:
            return
        if not wait:  # the control loop's hot path: no lock, a futex wake only if parked
            self._flush_asked += 1
            bell = self.doorbell
            if bell.waiting:
                bell.ring()
            return
        with self._flushed:
            self._flush_asked = target = self._flush_asked + 1
            self._flush_waiters += 1
            try:
                self.doorbell.ring()
                self._flushed.wait_for(
                    lambda: (self._flush_done >= target and not self._deferred)
                    or self._stopping or self._paused, timeout)
            finally:
                self._flush_waiters -= 1

    def _run(self) -> None:
        period = self._period
        next_tick = time.monotonic() + period if period else None
        # Parking is the default and the common case: straight to the bell, two calls fewer.
        idle = self.idle
        park = isinstance(idle, Park)
        wait_for, has_work = self.doorbell.wait_for, self._has_work
        while not self._stopping:
            timeout = None if next_tick is None else max(0.0, next_tick - time.monotonic())
            if self._holding:
                timeout = HOLD_POLL_S if timeout is None else min(timeout, HOLD_POLL_S)
            retry = self._retry
            if retry is not None:
                timeout = retry if timeout is None else min(timeout, retry)
            if park:
                wait_for(has_work, timeout)
            else:
                idle.idle(has_work, self._park, timeout)
            asked = self._flush_asked  # read once: a flush asked from now on is the next round's
            flush_all = asked != self._flush_done
            if next_tick is not None and time.monotonic() >= next_tick:
                flush_all = True
                next_tick += period  # type: ignore[operator]
                if next_tick < time.monotonic():  # overrun: skip, do not burst
                    next_tick = time.monotonic() + period  # type: ignore[operator]
            was_deferred = self._deferred
            self.rounds += 1
            try:
                with self._round:
                    self._send_pending(flush_all)
            except (OSError, ConnectionClosed) as exc:
                # A session that ended under this round (its socket closed or already gone)
                # must not end the thread: the reconnect supervisor resumes it on the next one.
                self.send_errors += 1
                log.warning("send failed: %s", exc)
            self._flush_done = asked
            if self._flush_waiters and (flush_all or was_deferred):
                with self._flushed:
                    self._flushed.notify_all()

    def _park(self, timeout: float | None) -> bool:
        return self.doorbell.wait_for(self._has_work, timeout)

    def _has_work(self) -> bool:
        if self._stopping:
            return True
        if self._paused:
            return False
        if self._flush_asked != self._flush_done:  # the common wake-up: Bridge.send()
            return True
        if self._credits and any(c.credit_due() for c in self._credits):
            return True
        wakers = self._wakers
        if not wakers:
            return False
        now = time.monotonic_ns()
        return any((s.immediate or s.deferred) and s.ready(now) for s in wakers)

    def _send_pending(self, flush_all: bool) -> None:
        if self._paused:
            return
        conn = self._conn
        packer = self._packer_for(conn)
        max_batch = self._batch_limit(conn)
        frames = bytearray()  # TCP frames of the round: credit, then values
        if self._credits:
            self._grant_credit(frames)
        parts = self._parts
        if parts:  # left by a round that failed before it sent them: lost with that round
            parts.clear()
        if self._handoff is not None:
            self._take_handoff(packer, parts)
        gathered = True  # the packer may hold parts added one by one: flush it
        if packer is not None and packer.one_call:
            # The short way: plain channels append their values as parts, and the round's
            # parts are encoded by one call into one datagram (or, too large, packed below).
            self.values_sent += take_plain(self._plain if flush_all else self._plain_immediate,
                                           parts, max_batch)
            others = self._others
            gathered = False
        else:
            others = self._sources
        if others:
            self._take_others(others, flush_all, conn, packer, frames, parts, max_batch)
        else:  # nothing that can hold, defer or wait for a rate
            self._holding, self._retry, self._deferred = False, None, False
        if parts:
            self.packets_sent += len(parts)
            assert packer is not None
            try:
                if not packer.send_parts(parts):  # too large together, or no bundles
                    gathered = True
                    for part in parts:
                        packet = as_packet(part)
                        refused = packer.add(packet)
                        if refused:
                            self._over_datagram(refused, packet.channel)
            finally:  # a failed send loses this round's parts, never resends them later
                parts.clear()
        if gathered and packer is not None:
            packer.flush()  # what was added one by one: one datagram (a bundle) again
        if frames:
            conn.send_tcp(frames)

    def _take_others(self, sources: tuple[OutgoingSource, ...], flush_all: bool,
                     conn: Connection, packer: DatagramPacker | None, frames: bytearray,
                     parts: list[Part], max_batch: int) -> None:
        """The sources with policies (and every source when the round cannot bundle):
        ``take`` applies them; TCP packets become frames, UDP packets parts of the round."""
        codec = conn.codec
        backed_up: bool | None = None  # asked of the kernel once per round, if needed
        holding = False
        deferred = False
        retry: float | None = None
        max_packet = -1  # the server's limit on a frame body, looked up once a TCP run needs it
        refused: list[tuple[int, int]] = []
        for src in sources:
            if not (flush_all or src.immediate or src.holding or src.deferred):
                continue
            busy = False
            tcp = src.transport == "tcp"
            if tcp and src.latest:
                if backed_up is None:
                    backed_up = conn.tcp is not None and congested(conn.tcp)
                busy = backed_up
            first_seq, stamps, values, repeated = src.take(busy)
            holding = holding or src.holding
            deferred = deferred or src.deferred
            if src.pacing is not None:
                wait = src.retry_in(time.monotonic_ns())
                if wait is not None and (retry is None or wait < retry):
                    retry = wait
            n = len(values)
            if n == 0:
                continue
            self.values_sent += n - repeated
            self.values_repeated += repeated
            if tcp:
                if max_packet < 0:
                    ack = conn.ack
                    max_packet = ack.limits.max_packet if ack is not None else DEFAULT_MAX_PACKET
                self.packets_sent += encode_run_into(codec, frames, src.channel_id, first_seq,
                                                     stamps, values, max_batch,
                                                     max_packet, refused)
                if refused:
                    self._too_large(src, refused, max_packet)
            elif packer is not None:
                parts.extend(packets_for(src.channel_id, first_seq, stamps, values, max_batch))
        self._holding = holding
        self._retry = retry
        self._deferred = deferred

    @staticmethod
    def _too_large(src: OutgoingSource, refused: list[tuple[int, int]], limit: int) -> None:
        """Values alone over the server's ``max_packet``: left out (a frame that long would end
        the session), said and counted in ``health().rejected``."""
        for seq, size in refused:
            log.warning("value %d of channel %d is %d bytes encoded, over the server's limit "
                        "of %d bytes (max_packet); not sent", seq, src.channel_id, size, limit)
        src.left_out(len(refused))
        refused.clear()

    def _grant_credit(self, frames: bytearray) -> None:
        """Credit frames for the flow-controlled incoming channels whose reader caught up."""
        codec = self._conn.codec
        for credit in self._credits:
            if credit.credit_due():
                credit.credited = limit = credit.credit_limit()
                codec.encode_frame_into(Credit(credit.channel_id, limit), frames)

    def _packer_for(self, conn: Connection) -> DatagramPacker | None:
        """The packer of the current session (codec and token change on a new session)."""
        ack = conn.ack
        if ack is None or conn.udp is None:
            return None
        packer = self._packer
        if packer is None or packer.codec is not conn.codec or packer.token != ack.token:
            if packer is not None:
                self.datagrams_sent += packer.datagrams
            packer = self._packer = DatagramPacker(
                conn.codec, ack.token, DATAGRAM_BUDGET, conn.send_udp, limit=MAX_DATAGRAM,
                bundles=bool(conn.udp_flags & FLAG_BUNDLES), flags=conn.udp_flags)
        return packer

    def _batch_limit(self, conn: Connection) -> int:
        """The current session's ``max_batch`` (its ack's), else the one given at start."""
        ack = conn.ack
        return max(1, ack.limits.max_batch) if ack is not None else self._max_batch

    @property
    def datagrams(self) -> int:
        """Value datagrams sent so far (a bundle of every UDP channel counts once)."""
        return self.datagrams_sent + (self._packer.datagrams if self._packer else 0)

    def _over_datagram(self, n: int, channel: int) -> None:
        """``n`` values of ``channel`` each too large for a datagram: not sent, said and
        counted in its ``health().rejected`` (as a TCP value over ``max_packet`` is)."""
        log.warning("%d value(s) on channel %d too large for a datagram; dropped", n, channel)
        for source in self._sources:
            if source.channel_id == channel:
                source.left_out(n)

    # -- inline rounds (module docstring): a caller's thread runs the round ------------------

    def send_inline(self) -> bool:
        """Caller's thread: run the round here if that is safe; False: it could not, ring
        the send thread (``flush``). Never waits for anything (module docstring)."""
        if self._paused or self._stopping or self._handoff or self._in_hrt():
            self.inline_fallbacks += 1
            return False
        lock = self._round
        if not lock.acquire(False):  # the send thread is in a round: it gets this one too
            self.inline_fallbacks += 1
            return False
        try:
            done = self._inline_round()
        finally:
            lock.release()
        if not done:
            self.inline_fallbacks += 1
        return done

    def _in_hrt(self) -> bool:
        """The caller is a hard-real-time process: no inline round (warned once)."""
        info = current_process()
        if info is None or not info.hrt:
            return False
        if not self._hrt_warned:
            self._hrt_warned = True
            warnings.warn(RealTimeWarning(
                f"hard-real-time process {info.name!r} called send(inline=True): sent by the "
                "send thread instead (HRT code makes no system call for the network)"),
                stacklevel=4)  # _in_hrt <- send_inline <- Bridge.send <- caller
        return True

    def _inline_round(self) -> bool:
        """``send_inline`` holding ``_round``: take the plain channels, send one datagram."""
        packer = self._packer_for(self._conn)
        # Checked again under the lock: a source added, a round handed over meanwhile.
        if (packer is None or not packer.one_call or packer.sealed or packer.pending
                or self._handoff or self._paused):
            return False
        parts = self._parts
        if parts:  # left by a round that failed before it sent them (as in _send_pending)
            parts.clear()
        taken = take_plain(self._plain, parts, self._batch_limit(self._conn))
        if not parts:
            return not self._others_waiting()
        self.values_sent += taken
        try:
            if packer.send_parts(parts, self._send_nowait):
                self.packets_sent += len(parts)
                self.inline_rounds += 1
                parts.clear()
                return not self._others_waiting()
        except BlockingIOError:  # the socket buffer is full: the send thread may wait, not us
            pass
        except (OSError, ConnectionClosed) as exc:  # as the thread: this round is lost, counted
            parts.clear()
            self.send_errors += 1
            log.warning("send failed: %s", exc)
            return not self._others_waiting()
        self._handoff = (packer, parts[:])  # more than a datagram, or EAGAIN: the thread's
        parts.clear()
        self.inline_handoffs += 1
        return False

    def _others_waiting(self) -> bool:
        """A channel with a policy, or on TCP, has something for a round: the thread's."""
        others = self._others
        return bool(others) and any(s.pending() or s.holding or s.deferred for s in others)

    def _send_nowait(self, data: bytes) -> None:
        self._conn.send_udp(data, _DONTWAIT)

    def _take_handoff(self, packer: DatagramPacker | None, parts: list[Part]) -> None:
        """Send thread: an inline round's parts go first (they were taken before anything
        waiting now); a session that ended since then takes them with it (counted)."""
        assert self._handoff is not None
        owner, handed = self._handoff
        self._handoff = None
        if owner is packer:
            parts.extend(handed)
        else:
            self.send_errors += 1
            log.warning("send failed: %d part(s) handed over by send(inline=True) ended "
                        "with their session", len(handed))

    def close(self) -> None:
        """Flush what is waiting, then stop and join the thread."""
        if self._io_thread.is_alive():
            self.flush(wait=True, timeout=2.0)
        self._stopping = True
        self.doorbell.ring()
        if self._io_thread.is_alive():
            self._io_thread.join(5.0)


def packets_for(channel: int, first_seq: int, stamps: list[int], values: list[object],
             max_batch: int) -> list[Value | Batch]:
    if len(values) == 1:
        return [Value(channel, first_seq, stamps[0], values[0])]
    if max_batch == 1:  # one value per packet: a Value is what a batch of one means
        return [Value(channel, first_seq + i, s, v)
                for i, (s, v) in enumerate(zip(stamps, values, strict=True))]
    return [
        Batch(channel, first_seq + i, stamps[i : i + max_batch], values[i : i + max_batch])
        for i in range(0, len(values), max_batch)
    ]
