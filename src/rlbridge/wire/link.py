"""Liveness and link quality of one peer, as a pure function of time.

Theory of operation (aioquic-style: time is a parameter). Both ends send a heartbeat every
``heartbeat_ns``, also while data flows, because a heartbeat carries the echo that measures the
round-trip time and, on UDP, keeps the peer's address fresh. Every packet received
refreshes ``last_rx``. The link is CONNECTED while the peer was heard within 1.5 periods,
DEGRADED after that, and LOST once ``timeout_ns`` passes in silence (default: three periods, so a
dead peer is noticed within three heartbeat periods). The I/O shim asks :meth:`next_deadline`,
arms one timer for it, and calls :meth:`poll` when it fires; tests move a fake clock instead.

Heartbeats also carry wall-clock stamps (``wall_ns`` and two echoes), from which
:attr:`LinkMonitor.clock` estimates the peer's clock offset (wire/clock.py): callers that
pass ``wall_ns`` to :meth:`make_heartbeat` and :meth:`on_heartbeat` get value ages that are
correct across hosts to within half the round-trip time.
"""

from __future__ import annotations

from dataclasses import dataclass

from rlbridge._compat import StrEnum
from rlbridge.wire.clock import ClockOffset
from rlbridge.wire.packets import Heartbeat


class LinkState(StrEnum):
    """What control code can branch on without knowing the protocol."""

    CONNECTED = "connected"
    DEGRADED = "degraded"
    LOST = "lost"


@dataclass(frozen=True, slots=True)
class LinkStats:
    """A snapshot of one link's health, in nanoseconds (``-1`` when not measured yet)."""

    state: LinkState
    rtt_ns: int
    rtt_jitter_ns: int
    silence_ns: int
    heartbeats_sent: int
    heartbeats_received: int
    #: Peer's wall clock minus ours (0 until measured) and its error bound (-1: unknown).
    clock_offset_ns: int = 0
    clock_error_ns: int = -1


class LinkMonitor:
    """Heartbeat schedule, watchdog and RTT estimate for one peer (RFC 6298-style smoothing)."""

    def __init__(self, now_ns: int, heartbeat_ns: int, timeout_ns: int | None = None) -> None:
        if heartbeat_ns <= 0:
            raise ValueError("heartbeat period must be positive")
        self.heartbeat_ns = heartbeat_ns
        self.timeout_ns = timeout_ns if timeout_ns is not None else 3 * heartbeat_ns
        if self.timeout_ns <= heartbeat_ns:
            raise ValueError("watchdog timeout must be longer than one heartbeat period")
        self._last_rx = now_ns
        self._next_tx = now_ns
        self._peer_sent = 0
        self._peer_rx_at = now_ns
        self._srtt = -1
        self._rttvar = -1
        self._sent = 0
        self._received = 0
        self._lost = False
        self._peer_wall = 0
        self._peer_wall_rx = 0
        #: Peer clock minus ours, from the heartbeats' wall-clock fields.
        self.clock = ClockOffset()

    def on_receive(self, now_ns: int) -> None:
        """Any packet from the peer proves it is alive."""
        self._last_rx = now_ns
        self._lost = False

    def on_heartbeat(self, hb: Heartbeat, now_ns: int, wall_ns: int = 0) -> None:
        """Record the peer's stamp (to echo) and, if it echoed ours, a round-trip sample.

        ``wall_ns`` is our CLOCK_REALTIME now; with it, a heartbeat that echoes our wall
        stamp is one clock-offset sample (0 skips the clock estimate).
        """
        self.on_receive(now_ns)
        self._received += 1
        self._peer_sent = hb.sent_ns
        self._peer_rx_at = now_ns
        if wall_ns and hb.wall_ns:
            self._peer_wall, self._peer_wall_rx = hb.wall_ns, wall_ns
            if hb.echo_wall_ns and hb.echo_rx_wall_ns:
                self.clock.add(hb.echo_wall_ns, hb.echo_rx_wall_ns, hb.wall_ns, wall_ns)
        if hb.echo_ns > 0 and hb.echo_ns <= now_ns:
            sample = now_ns - hb.echo_ns
            if self._srtt < 0:
                self._srtt, self._rttvar = sample, sample // 2
            else:
                self._rttvar += (abs(self._srtt - sample) - self._rttvar) // 4
                self._srtt += (sample - self._srtt) // 8

    def heartbeat_due(self, now_ns: int) -> bool:
        return now_ns >= self._next_tx

    def make_heartbeat(self, now_ns: int, wall_ns: int = 0) -> Heartbeat:
        """The heartbeat to send now; it echoes the peer's last stamp, aged by our hold time.

        ``wall_ns`` (our CLOCK_REALTIME, 0: leave the clock fields out) lets the peer
        estimate the clock offset: the heartbeat carries it and echoes the peer's last wall
        stamp with the wall time it arrived.
        """
        self._next_tx = now_ns + self.heartbeat_ns
        self._sent += 1
        echo = 0
        if self._peer_sent:
            # The peer subtracts nothing: we echo its own stamp shifted by how long we held it,
            # so its RTT sample excludes our heartbeat-period wait.
            echo = self._peer_sent + (now_ns - self._peer_rx_at)
        if not wall_ns:
            return Heartbeat(sent_ns=now_ns, echo_ns=echo)
        return Heartbeat(now_ns, echo, wall_ns, self._peer_wall, self._peer_wall_rx)

    def state(self, now_ns: int) -> LinkState:
        silence = now_ns - self._last_rx
        if silence >= self.timeout_ns:
            return LinkState.LOST
        if silence * 2 >= self.heartbeat_ns * 3:
            return LinkState.DEGRADED
        return LinkState.CONNECTED

    def next_deadline(self, now_ns: int) -> int:
        """The earliest time at which :meth:`state` or :meth:`heartbeat_due` can change."""
        # A threshold already crossed changes nothing any more: a lost link waits for the next
        # heartbeat, not for ``now`` (which would make the caller's timer spin). No list or
        # generator: the receive thread asks this after every wake-up.
        deadline = self._next_tx
        last_rx = self._last_rx
        degraded_at = last_rx + (self.heartbeat_ns * 3) // 2
        if now_ns < degraded_at < deadline:
            deadline = degraded_at
        lost_at = last_rx + self.timeout_ns
        if now_ns < lost_at < deadline:
            deadline = lost_at
        return deadline if deadline > now_ns else now_ns

    @property
    def rtt_ns(self) -> int:
        """Smoothed round-trip time (-1 until measured); one load, for hot paths."""
        return self._srtt

    def stats(self, now_ns: int) -> LinkStats:
        return LinkStats(
            state=self.state(now_ns),
            rtt_ns=self._srtt,
            rtt_jitter_ns=self._rttvar,
            silence_ns=now_ns - self._last_rx,
            heartbeats_sent=self._sent,
            heartbeats_received=self._received,
            clock_offset_ns=self.clock.offset_ns,
            clock_error_ns=self.clock.error_bound_ns,
        )
