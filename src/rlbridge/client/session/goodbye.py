"""The goodbye of ``Bridge.close``: the server takes the last values before the session ends.

Why. The server reads its TCP and UDP sockets independently (docs/protocol.md 8.4): a
``Disconnect`` over TCP can be handled before datagrams sent ahead of it, which then carry a
dead token and are dropped, never published. A burst written just before ``close()`` lost
its tail that way, silently. So the goodbye waits its turn, bounded, after the send thread's
final flush. What is *in flight* is known per publish channel: the values numbered in this
binding beyond the ``next_seq`` of the server's last ``LossReport`` (every channel the SDK
binds asks for reports).

* Nothing in flight over UDP: ``Disconnect`` over TCP at once, as always. The server reads a
  TCP connection in order, so it comes after the TCP values, and ``close()`` stays fast. (A
  UDP-only session's goodbye is a datagram, behind the values anyway.)
* UDP values in flight: ``Disconnect`` over UDP, behind them on the same socket, and wait
  for the server to close the TCP connection, which it does on handling it: every datagram
  that reached it before the goodbye was taken. Resent while waiting (every two round trips,
  at most a heartbeat period): a goodbye the link loses must not cost the whole bound.
* TCP values in flight too: the server stops reading TCP when a UDP goodbye ends the
  session, so it could overtake *those*. First wait for loss reports to cover the TCP
  channels (one heartbeat period, 200 ms by default), then as above.

The bound: the session's link timeout (``ConnectAck.timeout_ms``, 600 ms by default, the
silence after which either side gives the link up), at most the ``timeout`` given to
``Bridge.connect``. At the bound the goodbye goes over TCP (an info line says so), and what
is still unconfirmed on a UDP channel is not silent: it is counted in the channel's
``health().lost`` and a warning names the channel. Closing from the receive thread (which
cannot wait for itself) counts the same at once. A datagram the network dropped before a
goodbye that was confirmed is a gap the server never sees (no later value): that is UDP, as
at any other pause.

A channel's ``close()`` races the same way: its ``TopicClose`` over TCP can overtake its last
datagrams, which the server then drops (the channel is gone). Before it, :func:`deliver_last`
sends the values still in the channel, then waits, with the same bound, for the loss reports
to cover them (not a ``TopicClose`` over UDP: it has no answer, so one the link lost would
leave the binding). What they never covered is counted and said the same way. Nothing in
flight, a TCP channel or a UDP-only session (the ``TopicClose`` is behind the values): no
wait.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence

from rlbridge.client.channels.outgoing import OutgoingChannel
from rlbridge.client.session.connection import GOODBYE, Connection

log = logging.getLogger("rlbridge.client")


class Goodbye:
    """Says ``Bridge.close``'s goodbye on a connection (``Connection.close(goodbye)``)."""

    def __init__(self, channels: Sequence[OutgoingChannel], reported: threading.Condition,
                 ) -> None:
        self._channels = tuple(channels)
        #: Notified by the receive thread after each loss report (client/session/feedback.py).
        self._reported = reported

    def __call__(self, conn: Connection) -> None:
        bound = _bound(conn)
        deadline = time.monotonic() + bound
        if conn.control != "tcp" or conn.udp is None or not self._waiting("udp"):
            conn.send_control(GOODBYE)  # UDP-only: behind the datagrams already
            return
        within = f"within {bound:.3g} s"
        udp = [c for c in self._channels if c.transport == "udp"]
        # Counted before the goodbye on TCP, which may fail: a broken link counts them too.
        if not conn.receiving:  # closing from the receive thread, or it ended: no answer
            _count_unconfirmed(udp, "before the session ended")
            conn.send_control(GOODBYE)
            return
        tcp = [c for c in self._channels if c.transport == "tcp"]
        if self._waiting("tcp") and not _reports_cover(tcp, self._reported, conn, deadline):
            log.info("closing: no loss report covered the TCP values %s; goodbye over TCP",
                     within)
            _count_unconfirmed(udp, within)
            conn.send_control(GOODBYE)  # behind the TCP values, which it keeps
            return
        if not self._waiting("udp"):  # the reports that covered TCP covered UDP too
            conn.send_control(GOODBYE)
            return
        if not self._over_udp(conn, deadline):
            log.info("closing: the server did not end the session on the goodbye over UDP %s; "
                     "goodbye over TCP", within)
            _count_unconfirmed(udp, within)
            conn.send_control(GOODBYE)

    def _waiting(self, transport: str) -> bool:
        """A channel on ``transport`` has values the server has not confirmed."""
        return any(c.transport == transport and c.unconfirmed() for c in self._channels)

    def _over_udp(self, conn: Connection, deadline: float) -> bool:
        """``Disconnect`` over UDP (resent) until the server hangs up the TCP connection;
        False at the deadline, or if a datagram cannot be sent."""
        resend = _slice(conn)
        while True:
            try:
                conn.send_udp_packet(GOODBYE)
            except OSError as exc:
                log.debug("goodbye over UDP not sent: %s", exc)
                return False
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            if conn.wait_hung_up(min(resend, left)):
                return True


def deliver_last(channel: OutgoingChannel, conn: Connection, reported: threading.Condition,
                 flush: Callable[[float], object]) -> None:
    """Before ``channel.close()`` unbinds it on a live session: its last values reach the
    server (module docstring). ``flush(timeout)`` hands the values still in the channel to the
    sockets (the send thread's ``flush(wait=True)``); ``reported`` is notified after each loss
    report, which must still be routed to the channel."""
    bound = _bound(conn)
    deadline = time.monotonic() + bound
    if channel.pending():
        flush(bound)
    if (channel.transport != "udp" or conn.control != "tcp" or conn.udp is None
            or not channel.unconfirmed()):
        return
    if not conn.receiving:  # closed from the receive thread, or it ended: no answer
        _count_unconfirmed([channel], "before its channel was unbound")
    elif not _reports_cover([channel], reported, conn, deadline):
        _count_unconfirmed([channel], f"within {bound:.3g} s")


def _bound(conn: Connection) -> float:
    """How long the last values may take: the link timeout, at most ``connect``'s."""
    ack = conn.ack
    assert ack is not None
    return min(conn.timeout, ack.timeout_ms / 1000)


def _reports_cover(channels: Sequence[OutgoingChannel], reported: threading.Condition,
                   conn: Connection, deadline: float) -> bool:
    """Wait for loss reports covering every value sent on ``channels``, until ``deadline``
    or the end of the session (checked every slice: a hang-up notifies nobody)."""
    def covered() -> bool:
        return not any(c.unconfirmed() for c in channels)

    with reported:
        while (left := deadline - time.monotonic()) > 0:
            if reported.wait_for(covered, min(left, _slice(conn))):
                return True
            if not conn.receiving:
                return False
    return covered()


def _count_unconfirmed(channels: Sequence[OutgoingChannel], when: str) -> None:
    """Every value of ``channels`` the server never confirmed: counted as lost, and said."""
    for channel in channels:
        count = channel.unconfirmed()
        if count:
            channel.not_confirmed(count)
            log.warning("closing: the server did not confirm the last %d value(s) of "
                        "channel %d (%s) %s; counted as lost (health().lost)",
                        count, channel.channel_id, channel.topic, when)


def _slice(conn: Connection) -> float:
    """How long to wait for an answer before asking again: two round trips, between 10 ms
    and a heartbeat period (a quarter of one while the round trip is unknown)."""
    ack, link = conn.ack, conn.link
    heartbeat = ack.heartbeat_ms / 1000 if ack is not None else 0.2
    rtt_ns = link.rtt_ns if link is not None else -1
    if rtt_ns < 0:
        return heartbeat / 4
    return min(heartbeat, max(0.01, 2 * rtt_ns / 1e9))
