"""Human-readable tables of the server's counters (what ``rlbridge stats`` prints).

The input is the body of a ``Stats`` reply: ``server`` totals, and over a TCP control path
``sessions``, each with its ``channels``. Columns are fixed so that scripts that read the text
get the same layout from every server; ``rlbridge stats --json`` is the stable format.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

SERVER_KEYS = ("sessions", "sessions_opened", "values_in", "values_out", "dropped", "late",
               "malformed", "bad_values", "errors_sent", "packets_in", "bytes_in", "bytes_out",
               "ros_lost")
SESSION_COLUMNS = (("id", "session"), ("name", "name"), ("state", "state"),
                   ("rtt_us", "rtt_us"), ("pkts_in", "packets_in"),
                   ("bytes_in", "bytes_in"), ("bytes_out", "bytes_out"),
                   ("values_in", "values_in"), ("values_out", "values_out"),
                   ("dropped", "dropped"), ("late", "late"), ("malformed", "malformed"),
                   ("ros_lost", "ros_lost"))
CHANNEL_COLUMNS = (("ch", "channel"), ("dir", "direction"), ("via", "transport"),
                   ("topic", "topic"), ("values_in", "values_in"),
                   ("values_out", "values_out"), ("dropped", "dropped"), ("late", "late"),
                   ("malformed", "malformed"), ("bad_values", "bad_values"),
                   ("ros_lost", "ros_lost"))


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:,.0f}" if abs(value) >= 100 else f"{value:.1f}"
    if isinstance(value, int) and not isinstance(value, bool):
        return f"{value:,}"
    return str(value)


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]], indent: str = "") -> list[str]:
    """Left-aligned text columns, numbers right-aligned."""
    cells = [[_cell(v) for v in row] for row in rows]
    numeric = [all(isinstance(r[i], int | float) or r[i] is None for r in rows)
               for i in range(len(headers))]
    widths = [max([len(h)] + [len(r[i]) for r in cells]) for i, h in enumerate(headers)]

    def line(values: Sequence[str]) -> str:
        parts = [v.rjust(w) if num and rows else v.ljust(w)
                 for v, w, num in zip(values, widths, numeric, strict=True)]
        return (indent + "  ".join(parts)).rstrip()

    return [line([h.upper() for h in headers]), *(line(r) for r in cells)]


def format_stats(body: dict[str, Any]) -> str:
    """Server totals, then one table row per session and, under it, one per channel."""
    server = body.get("server", {})
    out = ["server: " + ", ".join(f"{k} {_cell(server[k])}" for k in SERVER_KEYS if k in server)]
    sessions = body.get("sessions")
    if sessions is None:  # a UDP control path: only the asking session is included
        sessions = [body["session"]] if "session" in body else []
    for session in sessions:
        out.append("")
        out += table([h for h, _ in SESSION_COLUMNS],
                     [[session.get(k) for _, k in SESSION_COLUMNS]])
        channels = session.get("channels", {})
        if channels:
            rows = [[int(ch) if ch.isdigit() else ch,
                     *(c.get(k) for _, k in CHANNEL_COLUMNS[1:])]
                    for ch, c in sorted(channels.items(), key=lambda kv: int(kv[0]))]
            out += table([h for h, _ in CHANNEL_COLUMNS], rows, indent="    ")
    return "\n".join(out)
