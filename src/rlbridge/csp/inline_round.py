"""Inline rounds: ``Bridge.send(inline=True)`` runs the send round in the caller's thread.

Why. Waking the send thread (:mod:`rlbridge.csp.sender`) costs the caller a futex wake and the
thread its own wake-up before its ``sendto``: a cross-thread hand-off on every value's path,
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
sends it first in its next round (:meth:`InlineRounds._take_handoff`), before anything taken
later, so nothing is lost; a session that ended meanwhile takes it along, counted as a failed
round is.
"""

from __future__ import annotations

import logging
import socket
import threading
import warnings

from rlbridge.csp.connection import Connection, ConnectionClosed
from rlbridge.csp.outgoing import OutgoingChannel
from rlbridge.csp.plain_round import take_plain
from rlbridge.csp.process import current_process
from rlbridge.csp.send_sources import OutgoingSource
from rlbridge.errors import RealTimeWarning
from rlbridge.wire.bundle import DatagramPacker, Part

log = logging.getLogger("rlbridge.client")

_DONTWAIT = socket.MSG_DONTWAIT


class InlineRounds:
    """The part of :class:`~rlbridge.csp.sender.SendLoop` a caller's thread runs."""

    _conn: Connection
    _others: tuple[OutgoingSource, ...]
    _plain: tuple[OutgoingChannel, ...]
    _parts: list[Part]
    _max_batch: int
    _paused: bool
    _stopping: bool
    values_sent: int
    packets_sent: int
    send_errors: int

    def _init_inline(self) -> None:
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

    def _packer_for(self, conn: Connection) -> DatagramPacker | None:
        """The packer of ``conn``'s current session: the send loop's, which overrides this
        (a compiled base class needs the method itself, not only an annotation)."""
        raise NotImplementedError("SendLoop provides the session's packer")

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
        taken = take_plain(self._plain, parts, self._max_batch)
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
