"""A session's watchdog: one loop timer, armed at the link's next deadline, and re-armed.

The deadlines come from the sans-IO :class:`~rlbridge.wire.link.LinkMonitor` (time passed in);
this is the I/O shim that turns them into ``loop.call_at``. At each deadline the session is
either closed (nothing heard from the client within ``timeout_ms``) or sends its heartbeats,
followed by a ``LossReport`` for the publish channels whose first-hop counts moved (on UDP
when the session has it, like the heartbeat: the report is cumulative, a lost one is made good
by the next, and it keeps out of a busy TCP stream).
"""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING

from rlbridge.server.sinks import PacketSink
from rlbridge.wire.link import LinkState

if TYPE_CHECKING:
    from rlbridge.server.session_owner import SessionOwner


class SessionWatchdog:
    """Owned by one session: started by it, stopped by its ``close``."""

    def __init__(self, session: SessionOwner) -> None:
        self._session = session
        self._timer: asyncio.TimerHandle | None = None
        self._tcp_bytes_at_heartbeat = (-1, -1)
        self._arm()

    def beat(self) -> None:
        """Now, not at the next loop iteration: the first heartbeat, right after the
        ConnectAck, before any answer to packets that came in the same read (protocol.md 11)."""
        if self._timer is not None:
            self._timer.cancel()
        self._on_timer()

    def stop(self) -> None:
        """Cancel the pending deadline; the watchdog does not fire again."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _arm(self) -> None:
        now = time.monotonic_ns()
        deadline = self._session.link.next_deadline(now)
        loop = self._session.ctx.loop
        self._timer = loop.call_at(loop.time() + (deadline - now) / 1e9, self._on_timer)

    def _on_timer(self) -> None:
        s = self._session
        if s.closed:
            return
        now = time.monotonic_ns()
        if s.link.state(now) is LinkState.LOST:
            s.ctx.count("sessions_timed_out")
            s.close("watchdog: no packet from the client within "
                    f"{s.ctx.config.timeout_ms} ms", notify=True)
            return
        if s.link.heartbeat_due(now):
            hb = s.link.make_heartbeat(now, time.time_ns())
            sinks = self._heartbeat_sinks()
            for sink in sinks:
                sink.send(hb)
            for report in s.loss_reports() if sinks else ():
                sinks[-1].send(report)
            self._tcp_bytes_at_heartbeat = self._tcp_traffic()
            s.report_loss()
        self._arm()

    def _tcp_traffic(self) -> tuple[int, int]:
        s = self._session
        return getattr(s.tcp, "bytes_out", -1), s.tcp_bytes_in

    def _heartbeat_sinks(self) -> list[PacketSink]:
        """Both transports, but not a TCP connection that carried data either way since the
        last heartbeat while the client also has UDP (where heartbeats keep flowing): a
        heartbeat segment amid a stream makes the receiver's kernel delay its ACKs (it
        expects to piggyback them), and with Nagle on the sender then holds the next value
        for that delayed ACK, ~40 ms every heartbeat period (docs/evaluation.md)."""
        tcp, udp = self._session.tcp, self._session.udp
        if tcp is None or udp is None:
            return [s for s in (tcp, udp) if s is not None]
        if self._tcp_traffic() != self._tcp_bytes_at_heartbeat:
            return [udp]
        return [tcp, udp]
