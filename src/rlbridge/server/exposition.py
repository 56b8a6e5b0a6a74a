"""The server's counters in Prometheus' text exposition format (0.0.4), by its conventions.

Every family has a ``# HELP`` and a ``# TYPE`` line; names are ``rlbridge_<what>_<unit>``
with base units (``_seconds``, ``_bytes``) and ``_total`` on counters; labels are bounded:
``client`` (the name a client gives in its ``Hello``) and, per channel, ``topic``,
``direction`` and ``transport``, never a session id or a channel number, which change with
every reconnect. A client's series sum its open sessions and everything its closed ones counted
(:mod:`~rlbridge.server.ledger`, which also caps how many closed label sets are kept), so
counters only go up.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from rlbridge.server.ledger import (
    CHANNEL_COUNTERS,
    SESSION_COUNTERS,
    Ledger,
    channel_key,
    counters,
)

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

#: Server-wide numbers: report key -> (metric name, help). ``sessions`` is the one gauge.
SERVER = {
    "sessions": ("rlbridge_sessions", "Sessions open now."),
    "packets_in": ("rlbridge_received_packets_total",
                   "Packets received in sessions (TCP frames and datagrams that decoded)."),
    "bytes_in": ("rlbridge_received_bytes_total", "Bytes received in sessions' frames and "
                 "datagrams."),
    "bytes_out": ("rlbridge_sent_bytes_total", "Bytes sent in sessions' frames and datagrams."),
    "values_in": ("rlbridge_values_in_total", "Values published into the middleware."),
    "values_out": ("rlbridge_values_out_total", "Values the middleware gave subscribe channels."),
    "dropped": ("rlbridge_values_dropped_total", "Values dropped: a slow client's full queue, a "
                "value larger than a datagram, or values for a channel that is not bound."),
    "late": ("rlbridge_values_late_total", "Duplicate and overtaken values, not published."),
    "bad_values": ("rlbridge_values_rejected_total",
                   "Values refused for not being of their channel's type."),
    "malformed": ("rlbridge_malformed_packets_total", "Packets of sessions that did not decode."),
    "errors_sent": ("rlbridge_errors_sent_total", "Error packets sent to clients."),
    "ros_lost": ("rlbridge_values_ros_lost_total", "Values lost on the ROS side: messages a "
                 "full subscription queue dropped, values ROS refused to take."),
    "handoff_dropped_batches": ("rlbridge_handoff_dropped_batches_total",
                                "Middleware batches dropped on their way to the event loop."),
}
#: Per client: session counter -> (metric name suffix, help).
CLIENT = {
    "packets_in": ("received_packets_total", "Packets received from the client."),
    "bytes_in": ("received_bytes_total", "Bytes received from the client."),
    "bytes_out": ("sent_bytes_total", "Bytes sent to the client."),
    "malformed": ("malformed_packets_total", "Packets from the client that did not decode."),
    "errors_sent": ("errors_sent_total", "Error packets sent to the client."),
}
#: Per channel: counter -> (metric name suffix, help).
CHANNEL = {
    "values_in": ("values_in_total", "Values of a publish channel published."),
    "values_out": ("values_out_total", "Values the middleware gave a subscribe channel."),
    "dropped": ("values_dropped_total", "Values of a subscribe channel dropped (full queue)."),
    "late": ("values_late_total", "Duplicate and overtaken values, not published."),
    "lost": ("values_lost_total", "Values that never arrived (sequence gaps, publish channels)."),
    "duplicates": ("values_duplicate_total", "Values that arrived more than once."),
    "bad_values": ("values_rejected_total", "Values refused for not being of the type."),
    "malformed": ("malformed_packets_total", "Packets for the channel that did not decode."),
    "expired": ("values_expired_total", "Values older than max_age_ms, dropped."),
    "overtaken": ("values_overtaken_total", "Values replaced by a newer one (latest)."),
    "ros_lost": ("values_ros_lost_total", "Values lost on the ROS side: subscribe, messages "
                 "the server's subscription queue dropped or it took and could not hand on; "
                 "publish, values ROS refused."),
}
#: Per channel gauges in nanoseconds, exposed in seconds: ns key -> (suffix, help).
CHANNEL_SECONDS = {
    "one_way_ns": ("one_way_seconds", "Smoothed age of a publish channel's values on arrival, "
                   "clock-corrected (the largest over the client's sessions)."),
    "jitter_ns": ("jitter_seconds", "RFC 3550 interarrival jitter of a publish channel."),
}
LINK_STATES = ("connected", "degraded", "lost")


@dataclass
class _Family:
    kind: str
    help: str
    samples: dict[tuple[tuple[str, str], ...], float] = field(default_factory=dict)


class _Exposition:
    """Families in the order first added; samples of one label set added up."""

    def __init__(self) -> None:
        self.families: dict[str, _Family] = {}

    def add(self, name: str, kind: str, help_: str, labels: Iterable[tuple[str, str]],
            value: float, combine: str = "sum") -> None:
        family = self.families.setdefault(name, _Family(kind, help_))
        key = tuple(labels)
        old = family.samples.get(key)
        if old is None:
            family.samples[key] = value
        else:
            family.samples[key] = old + value if combine == "sum" else max(old, value)

    def text(self) -> str:
        lines: list[str] = []
        for name, family in self.families.items():
            lines.append(f"# HELP {name} {_escape_help(family.help)}")
            lines.append(f"# TYPE {name} {family.kind}")
            for labels, value in family.samples.items():
                lines.append(f"{name}{_labels(labels)} {_number(value)}")
        return "\n".join(lines) + "\n"


def render(report: Mapping[str, Any], ledger: Ledger | None = None) -> str:
    """The exposition text of ``SessionRegistry.stats()`` and the closed sessions' ledger."""
    out = _Exposition()
    ledger = ledger or Ledger()
    _server(out, report["server"])
    for session in report["sessions"]:
        _client(out, session)
    for client, totals in ledger.clients.items():
        who = (("client", client),)
        for key, (suffix, help_) in CLIENT.items():
            out.add(f"rlbridge_client_{suffix}", "counter", help_, who, totals.get(key, 0))
        out.add("rlbridge_client_sessions_opened_total", "counter",
                "Sessions the client has opened (a reconnect opens one).", who,
                totals.get("sessions", 0))
    for channel, sums in ledger.channels.items():
        labels = tuple(zip(("client", "topic", "direction", "transport"), channel, strict=True))
        for name, value in sums.items():
            suffix, help_ = CHANNEL[name]
            out.add(f"rlbridge_channel_{suffix}", "counter", help_, labels, value)
    return out.text()


def _server(out: _Exposition, server: Mapping[str, Any]) -> None:
    for key, value in server.items():
        if not isinstance(value, int | float) or isinstance(value, bool):
            continue
        name, help_ = SERVER.get(key, (f"rlbridge_{key}_total",
                                       f"Server event counter {key} (docs/protocol.md 13.2)."))
        out.add(name, "gauge" if key == "sessions" else "counter", help_, (), value)


def _client(out: _Exposition, session: Mapping[str, Any]) -> None:
    name = str(session.get("name", ""))
    who = (("client", name),)
    for key, value in counters(session, SESSION_COUNTERS).items():
        suffix, help_ = CLIENT[key]
        out.add(f"rlbridge_client_{suffix}", "counter", help_, who, value)
    out.add("rlbridge_client_sessions_opened_total", "counter",
            "Sessions the client has opened (a reconnect opens one).", who, 1)
    for state in LINK_STATES:
        out.add("rlbridge_client_sessions", "gauge", "Open sessions of the client, by link "
                "state (connected, degraded, lost).", (*who, ("state", state)),
                1 if session.get("state") == state else 0)
    rtt_us = session.get("rtt_us")
    if isinstance(rtt_us, int | float):
        out.add("rlbridge_client_rtt_seconds", "gauge", "Smoothed round-trip time of the "
                "client's link (heartbeats; the largest over its sessions).", who,
                rtt_us / 1e6, combine="max")
    out.add("rlbridge_client_tcp_queued_bytes", "gauge", "Bytes waiting in the server for the "
            "client's TCP connection.", who, session.get("tcp_queued_bytes", 0))
    for channel in session.get("channels", {}).values():
        labels = tuple(zip(("client", "topic", "direction", "transport"),
                           channel_key(name, channel), strict=True))
        out.add("rlbridge_channel_bindings", "gauge", "Channels bound now.", labels, 1)
        for counter, value in counters(channel, CHANNEL_COUNTERS).items():
            suffix, help_ = CHANNEL[counter]
            out.add(f"rlbridge_channel_{suffix}", "counter", help_, labels, value)
        for counter, value in counters(channel, CHANNEL_SECONDS).items():
            suffix, help_ = CHANNEL_SECONDS[counter]
            out.add(f"rlbridge_channel_{suffix}", "gauge", help_, labels, value / 1e9,
                    combine="max")


def _escape(value: object) -> str:
    return str(value).replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def _escape_help(text: str) -> str:
    return text.replace("\\", "\\\\").replace("\n", "\\n")


def _labels(labels: tuple[tuple[str, str], ...]) -> str:
    if not labels:
        return ""
    return "{" + ",".join(f'{k}="{_escape(v)}"' for k, v in labels) + "}"


def _number(value: float) -> str:
    """Integers exactly (``%g`` would print 1234567 as 1.23457e+06), floats in full."""
    if isinstance(value, int) or (isinstance(value, float) and value.is_integer()):
        return str(int(value))
    return repr(float(value))
