"""What the server says about a client's publish channels, routed to them.

Two packets come back from the server for the channels a client publishes (receive thread):

* ``Credit(channel, limit)``: a flow-controlled channel may send up to ``limit``; if that
  lets waiting values go, the send thread's doorbell rings.
* ``LossReport``: the first hop per channel (arrived, lost at the server, refused by its rate
  limit), every heartbeat period while the counts move. Each channel records it
  (``health().arrived`` and ``lost``; an adaptive rate limit follows it) and new loss becomes
  a :class:`~rlbridge.client.session.link_events.LinkEvent` naming the channel, so a flood that
  loses
  most of what it sends is visible to control code within a heartbeat period. ``Bridge.close``
  waits on :attr:`Feedback.reported` for the reports that cover its last values
  (:mod:`rlbridge.client.session.goodbye`).
"""

from __future__ import annotations

import threading

from rlbridge.client.channels.outgoing import OutgoingChannel
from rlbridge.client.session.link_events import LinkEvents
from rlbridge.csp.bell import Bell
from rlbridge.wire import LossReport


class Feedback:
    """Routes credit and loss reports to the Bridge's outgoing channels (by channel id)."""

    def __init__(self, outgoing: dict[int, OutgoingChannel], events: LinkEvents,
                 doorbell: Bell) -> None:
        self._outgoing = outgoing
        self._events = events
        self._doorbell = doorbell
        #: Notified after every loss report (the channels have taken it).
        self.reported = threading.Condition()

    def on_credit(self, channel: int, limit: int) -> None:
        out = self._outgoing.get(channel)
        if out is not None and out.on_credit(limit) and self._doorbell.waiting:
            self._doorbell.ring()

    def on_loss(self, report: LossReport) -> None:
        for loss in report.channels:
            out = self._outgoing.get(loss.channel)
            if out is None:
                continue
            lost = out.on_loss(loss)
            if lost > 0:
                total = loss.received + loss.lost
                self._events.emit_loss(loss.channel, lost, (
                    f"channel {loss.channel} ({out.topic}): {lost:,} values lost at the first "
                    f"hop since the last report; {loss.lost:,} of {total:,} since bound"
                    + (f", {loss.refused:,} refused by the server's rate limit"
                       if loss.refused else "")))
        with self.reported:
            self.reported.notify_all()
