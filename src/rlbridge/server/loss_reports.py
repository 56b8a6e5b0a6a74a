"""Which publish channels a session's next ``LossReport`` names (protocol.md 10.6).

Counts are cumulative, so only channels whose counts moved since the last report are named,
and each channel's last change is named once more in the next period: a report lost on UDP
is made good by the next one, and a channel that stopped changing costs nothing after that.
"""

from __future__ import annotations

from collections.abc import Mapping

from rlbridge.server.bindings import Inbound
from rlbridge.wire import ChannelLoss, LossReport

#: Channels per LossReport packet: a report of 64 fits one 1400-byte datagram.
REPORT_CHANNELS = 64


class LossReporter:
    """What the last report said per publish channel of one session."""

    def __init__(self) -> None:
        self._reported: dict[int, ChannelLoss] = {}
        #: Channels whose last change is sent once more.
        self._repeat: set[int] = set()

    def reports(self, inbound: Mapping[int, Inbound]) -> list[LossReport]:
        """The reports for this period (none when nothing moved)."""
        changed = []
        reported, repeat = self._reported, self._repeat
        for ch, binding in inbound.items():
            if not binding.request.loss_report:
                continue
            loss = binding.loss()
            if reported.get(ch) != loss:
                reported[ch] = loss
                repeat.add(ch)
                changed.append(loss)
            elif ch in repeat:
                repeat.discard(ch)
                changed.append(loss)
        return [LossReport(changed[i : i + REPORT_CHANNELS])
                for i in range(0, len(changed), REPORT_CHANNELS)]

    def forget(self, channel: int) -> None:
        """The channel was closed: a new binding under its number starts from nothing."""
        self._reported.pop(channel, None)
        self._repeat.discard(channel)
