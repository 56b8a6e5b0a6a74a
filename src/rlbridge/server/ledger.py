"""Counters by client and topic that outlive sessions, with a bounded number of label sets.

Metrics are labelled by *who* (the client's name from its ``Hello``) and *what* (a channel's
topic and direction), never by session id: a client that reconnects a hundred times is one
series, not a hundred. When a session or a channel closes, its counters move here, so a
client's counters never go back when it reconnects. What stays bounded: the label sets of
closed clients and channels. Beyond ``max_clients`` / ``max_channels`` of them, the oldest one
*that is not live now* is folded into the ``(other)`` label set (its counts are kept, under that
name), so the number of series a scrape returns is at most the open sessions' plus these caps.

Live first: a client connected now (or a channel bound now) keeps its own label set however
old its retired totals are. Folding it away would make its series drop to the current
session's counts, a counter going back, while clients that left stayed named. The ledger asks
``live`` (set by the session registry) only when it is over a cap.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Hashable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

#: The label value that absorbs closed clients and channels beyond the caps.
OTHER = "(other)"
#: Closed clients and closed channels remembered under their own labels (defaults).
MAX_CLIENTS = 64
MAX_CHANNELS = 512

#: Session counters that are totals (the rest of a session's numbers are gauges or labels).
SESSION_COUNTERS = ("packets_in", "bytes_in", "bytes_out", "malformed", "errors_sent")
#: Channel counters that are totals; health numbers such as ``rtt_ns`` are gauges.
CHANNEL_COUNTERS = ("values_in", "values_out", "dropped", "late", "lost", "duplicates",
                    "bad_values", "malformed", "expired", "overtaken", "ros_lost")

ChannelKey = tuple[str, str, str, str]  # client, topic, direction, transport
#: The clients with an open session and the channels bound now (``SessionRegistry.live``).
LiveLabels = tuple[Collection[str], Collection[ChannelKey]]


K = TypeVar("K", bound=Hashable)


def _nothing_live() -> LiveLabels:
    return (), ()


def channel_key(client: str, channel: Mapping[str, Any]) -> ChannelKey:
    """The labels of one channel's series: client name, topic, direction, transport."""
    return (client, str(channel.get("topic", "")), str(channel.get("direction", "")),
            str(channel.get("transport", "")))


def counters(values: Mapping[str, Any], names: Iterable[str]) -> dict[str, int]:
    """The non-negative integer counters among ``names`` (``-1`` means "not measured")."""
    out: dict[str, int] = {}
    for name in names:
        value = values.get(name)
        if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
            out[name] = value
    return out


def _add(into: dict[str, int], values: Mapping[str, int]) -> None:
    for key, value in values.items():
        into[key] = into.get(key, 0) + value


@dataclass
class Ledger:
    """Totals of closed sessions by client, and of closed channels by client and topic."""

    max_clients: int = MAX_CLIENTS
    max_channels: int = MAX_CHANNELS
    #: Insertion order is age: the first entries are folded into ``(other)`` first.
    clients: dict[str, dict[str, int]] = field(default_factory=dict)
    channels: dict[ChannelKey, dict[str, int]] = field(default_factory=dict)
    #: Who is connected and what is bound now: never folded while over the caps.
    live: Callable[[], LiveLabels] = _nothing_live

    def retire_session(self, client: str, stats: Mapping[str, Any]) -> None:
        """A session closed: keep its counters under its client's name."""
        totals = self.clients.pop(client, {})  # re-inserted: now the youngest
        _add(totals, counters(stats, SESSION_COUNTERS))
        totals["sessions"] = totals.get("sessions", 0) + 1
        self.clients[client] = totals
        if len(self.clients) > self.max_clients:
            _fold(self.clients, self.max_clients, OTHER, set(self.live()[0]) | {client})

    def retire_channel(self, client: str, stats: Mapping[str, Any]) -> None:
        """A channel closed (unbound, or with its session): keep its counters."""
        key = channel_key(client, stats)
        totals = self.channels.pop(key, {})
        _add(totals, counters(stats, CHANNEL_COUNTERS))
        self.channels[key] = totals
        if len(self.channels) > self.max_channels:
            _fold(self.channels, self.max_channels, (OTHER, OTHER, OTHER, OTHER),
                  set(self.live()[1]) | {key})


def _fold(entries: dict[K, dict[str, int]], cap: int, other: K, keep: set[K]) -> None:
    """Fold the oldest entries not in ``keep`` into ``other`` until ``cap`` or none is left.

    Only live entries (and the one just retired) can hold it above the cap: at most the open
    sessions' worth.
    """
    keep = keep | {other}
    for key in [k for k in entries if k not in keep]:
        if len(entries) <= cap:
            return
        _add(entries.setdefault(other, {}), entries.pop(key))
