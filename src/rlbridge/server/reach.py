"""A session's reach into the ROS graph beyond topics: services, goals, ROS-side loss reports.

The session routes every packet of :data:`REACH_PACKETS` here; calls and offers are
:mod:`~rlbridge.server.services`, goals :mod:`~rlbridge.server.actions`. Channels that offer
a service or carry a goal share the session's channel ids with its topic channels, so
:meth:`SessionReach.owns` is part of every "is this channel in use" check.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from rlbridge.server.actions import SessionGoals
from rlbridge.server.bindings import Inbound, Outbound
from rlbridge.server.services import SessionServices
from rlbridge.server.sinks import PacketSink
from rlbridge.wire import (
    GoalCancel,
    GoalSend,
    RosLoss,
    ServiceCall,
    ServiceOffer,
    ServiceReply,
)

if TYPE_CHECKING:
    from rlbridge.server.session_owner import SessionOwner

#: The client packets a session hands to :class:`SessionReach`.
REACH_PACKETS = (ServiceCall, ServiceOffer, ServiceReply, GoalSend, GoalCancel)
ReachPacket = ServiceCall | ServiceOffer | ServiceReply | GoalSend | GoalCancel


class SessionReach:
    """Service calls, provided services and goals of one session, and its loss reports."""

    def __init__(self, session: SessionOwner) -> None:
        self._session = session
        #: Service calls in flight and services this client provides.
        self.services = SessionServices(session)
        self.goals = SessionGoals(session)
        self._loss_reported: dict[int, int] = {}

    def handle(self, packet: ReachPacket, via: PacketSink | None) -> None:
        s = self._session
        if isinstance(packet, ServiceCall):
            self.services.call(packet, via)
        elif isinstance(packet, ServiceReply):
            self.services.reply(packet, via)
        elif isinstance(packet, GoalCancel):
            self.goals.cancel(packet.channel, via)
        else:
            ch = packet.channel
            in_use = ch in s.inbound or ch in s.outbound or self.owns(ch)
            if isinstance(packet, ServiceOffer):
                self.services.offer(packet, via, in_use)
            else:
                self.goals.send(packet, via, in_use)

    def owns(self, channel: int) -> bool:
        """The channel offers a service or carries a goal."""
        return channel in self.services.offers or channel in self.goals.goals

    def withdraw(self, channel: int) -> bool:
        """``TopicClose`` of an offer's channel; False if the channel offers nothing."""
        return self.services.withdraw(channel) is not None

    def report_loss(self) -> None:
        """Tell the client of each topic channel whose ROS-side loss grew since the last
        report (``RosLoss``; the watchdog calls this every heartbeat period)."""
        s = self._session
        bindings: list[tuple[int, Inbound | Outbound]] = [*s.inbound.items(),
                                                          *s.outbound.items()]
        for ch, binding in bindings:
            lost = binding.ros_lost
            if lost != self._loss_reported.get(ch, 0):
                self._loss_reported[ch] = lost
                s.send_control(RosLoss(ch, lost))

    def close(self) -> None:
        self.services.close()
        self.goals.close()

    def stats(self) -> dict[str, int]:
        return self.services.stats()

    def channel_stats(self) -> dict[str, dict[str, Any]]:
        return {**self.services.channel_stats(), **self.goals.channel_stats()}
