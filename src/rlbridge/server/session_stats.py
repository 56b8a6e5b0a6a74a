"""A session's counters as the client and the operator read them: the ``Stats`` reply, and
totals that never go back when a channel closes.

Kept apart from :mod:`~rlbridge.server.session`, which routes packets: this module only reads
numbers the session hands it, so it needs neither the session's type nor its transports.
"""

from __future__ import annotations

from typing import Any

from rlbridge.server.context import ServerContext
from rlbridge.wire import Stats

__all__ = ["CHANNEL_TOTALS", "ChannelTotals", "stats_reply"]

#: Per-channel counters a session (and the server) also reports as totals.
CHANNEL_TOTALS = ("values_in", "values_out", "dropped", "late", "bad_values", "ros_lost")


class ChannelTotals:
    """The totals of a session's channels, the closed ones included."""

    def __init__(self) -> None:
        self.retired: dict[str, int] = dict.fromkeys(CHANNEL_TOTALS, 0)

    def retire(self, channel: dict[str, Any]) -> None:
        """Keep a closing channel's counts, so the session's totals never go back."""
        for key in CHANNEL_TOTALS:
            self.retired[key] += channel.get(key, 0)

    def totals(self, channels: dict[str, dict[str, Any]]) -> dict[str, int]:
        """The retired counts plus those of the channels still open."""
        totals = dict(self.retired)
        for channel in channels.values():
            for key in CHANNEL_TOTALS:
                totals[key] += channel.get(key, 0)
        return totals


def stats_reply(ctx: ServerContext, session: dict[str, Any], *, over_tcp: bool,
                sees_all: bool, services: bool) -> Stats:
    """Answer ``Stats``: this session, and over TCP every session and the server totals.

    A datagram cannot hold a thousand channels' counters, so a UDP control path gets this
    session's counters and the server's counters only. A client sees only its own session
    unless its identity may see all (server/authz.py).
    """
    body: dict[str, Any] = {"session": session, "server": dict(ctx.counters),
                            "topics": [list(t) for t in ctx.adapter.topics()]}
    if services:
        body["services"] = [list(t) for t in ctx.adapter.services()]
    if ctx.report is not None:
        report = ctx.report()
        body["server"] = report["server"]
        if over_tcp:
            sessions = report["sessions"]
            if not sees_all:
                sessions = [s for s in sessions if s["session"] == session["session"]]
            body["sessions"] = sessions
    return Stats(body)
