"""``rlbridge topic pub`` exits 0 only when the server took every value it published.

Sending is not delivering: the server may refuse a value (not the channel's type, too old,
over ``--max-rate``) and a UDP datagram may not arrive at all. After the last send, the
command asks the server for its own session's counters until the channel's ``values_in``
reaches the number sent, or the counters settle short of it, and says which it was.
"""

from __future__ import annotations

import time
from typing import Any

from rlbridge.wire import RlbridgeError

#: Seconds to wait for the server to count the values (UDP may still be in flight).
CONFIRM_TIMEOUT_S = 2.0
POLL_S = 0.05


class NotDelivered(RlbridgeError):
    """The server did not take every value ``topic pub`` sent; the message says how many."""


def channel_counters(stats: dict[str, Any], channel_id: int) -> dict[str, int]:
    """This session's counters for ``channel_id`` from a ``Bridge.server_stats()`` reply."""
    session = stats.get("session") or {}
    counters: dict[str, int] = session.get("channels", {}).get(str(channel_id), {})
    return counters


def confirm_delivery(bridge: Any, channel: Any, sent: int,
                     timeout: float = CONFIRM_TIMEOUT_S) -> None:
    """Return once the server counted ``sent`` values on ``channel``; else raise why not."""
    deadline = time.monotonic() + timeout
    while True:
        counts = channel_counters(bridge.server_stats(), channel.channel_id)
        accepted = counts.get("values_in", 0)
        if accepted >= sent:
            return
        refused = {k: counts.get(k, 0) for k in ("bad_values", "expired", "late")}
        # Over TCP the reply follows the values on the same stream: they are all counted.
        settled = channel.transport == "tcp" or accepted + sum(refused.values()) >= sent
        if settled or time.monotonic() >= deadline:
            raise NotDelivered(_explain(channel, sent, accepted, refused, timeout))
        time.sleep(POLL_S)


def _explain(channel: Any, sent: int, accepted: int, refused: dict[str, int],
             timeout: float) -> str:
    what = f"the server took {accepted} of {sent} value(s) published on {channel.topic}"
    field = f"'{channel.field}' of " if channel.field else ""
    reasons = []
    if refused["bad_values"]:
        reasons.append(f"{refused['bad_values']} not a valid {field}{channel.msg_type}")
    if refused["expired"]:
        reasons.append(f"{refused['expired']} older than the channel's max_age_ms")
    if refused["late"]:
        reasons.append(f"{refused['late']} duplicate or out of order")
    missing = sent - accepted - sum(refused.values())
    if missing > 0:
        hint = (" (over the server's --max-rate, or lost: UDP does not retransmit; "
                "--transport tcp to be sure)" if channel.transport == "udp"
                else " (over the server's --max-rate?)")
        reasons.append(f"{missing} not counted within {timeout:g} s{hint}")
    return f"{what}: {'; '.join(reasons)}"
