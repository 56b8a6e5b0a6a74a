"""An optional Prometheus endpoint: ``GET /metrics`` in the text exposition format (0.0.4).

It is served by the server's own asyncio loop, so a scrape reads the live counters on the thread
that owns them, with no lock and no copy across threads. ``prometheus_client`` was not used: its
HTTP server runs on a thread of its own, which would have to read session state owned by the
loop (or hop into it per scrape), and its metric objects would duplicate counters the sessions
keep anyway. The responder is deliberately tiny: one request per connection, a bounded request
head, a deadline on reading it, then the connection is closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable, Iterator
from typing import Any

log = logging.getLogger("rlbridge.server")

#: Longest request head accepted, and how long a client may take to send it.
MAX_REQUEST = 8192
REQUEST_TIMEOUT_S = 5.0
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

#: Numbers that are gauges (they go down); every other number is a counter (``_total``).
GAUGES = {"sessions", "rtt_us", "tcp_queued_bytes"}
#: Per-channel labels taken from the channel's counters dict (everything else numeric is a value).
CHANNEL_LABELS = ("direction", "topic", "transport")

Report = Callable[[], dict[str, Any]]


def _escape(value: object) -> str:
    return str(value).replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def _labels(labels: dict[str, object]) -> str:
    return "{" + ",".join(f'{k}="{_escape(v)}"' for k, v in labels.items()) + "}"


def _numbers(counters: dict[str, Any]) -> Iterator[tuple[str, float]]:
    for key, value in counters.items():
        if isinstance(value, int | float) and not isinstance(value, bool):
            yield key, value


def render(report: dict[str, Any]) -> str:
    """The exposition text of ``SessionRegistry.stats()``: server, session and channel series.

    Series of one metric name are written together under one ``# TYPE`` line, as the format
    requires; sessions and channels are told apart by labels.
    """
    families: dict[str, tuple[str, list[str]]] = {}

    def add(name: str, kind: str, labels: dict[str, object], value: float) -> None:
        family = families.setdefault(name, (kind, []))
        family[1].append(f"{name}{_labels(labels) if labels else ''} {value:g}")

    for key, value in _numbers(report["server"]):
        if key in GAUGES:
            add(f"rlbridge_{key}", "gauge", {}, value)
        else:
            add(f"rlbridge_{key}_total", "counter", {}, value)
    for session in report["sessions"]:
        who = {"session": session["session"], "name": session["name"]}
        for key, value in _numbers(session):
            if key in GAUGES:
                add(f"rlbridge_session_{key}", "gauge", who, value)
            elif key != "session":
                add(f"rlbridge_session_{key}_total", "counter", who, value)
        for channel_id, channel in session["channels"].items():
            labels = {**who, "channel": channel_id,
                      **{k: channel[k] for k in CHANNEL_LABELS if k in channel}}
            for key, value in _numbers(channel):
                add(f"rlbridge_channel_{key}_total", "counter", labels, value)
    lines: list[str] = []
    for name, (kind, samples) in families.items():
        lines.append(f"# TYPE {name} {kind}")
        lines.extend(samples)
    return "\n".join(lines) + "\n"


class MetricsEndpoint:
    """The listening socket and its handler; ``close`` is called by the server's shutdown."""

    def __init__(self, report: Report) -> None:
        self._report = report
        self._server: asyncio.Server | None = None

    @property
    def port(self) -> int:
        assert self._server is not None, "metrics endpoint not started"
        port: int = self._server.sockets[0].getsockname()[1]
        return port

    async def start(self, host: str, port: int) -> MetricsEndpoint:
        self._server = await asyncio.start_server(self._handle, host, port, limit=MAX_REQUEST,
                                                  reuse_address=True)
        log.info("metrics on http://%s:%d/metrics", host, self.port)
        return self

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            try:
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), REQUEST_TIMEOUT_S)
            except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError):
                self._respond(writer, 400, "Bad Request", "bad or incomplete request\n")
                return
            parts = head.split(b"\r\n", 1)[0].split()
            if len(parts) != 3 or not parts[2].startswith(b"HTTP/"):
                self._respond(writer, 400, "Bad Request", "bad request line\n")
            elif parts[0] not in (b"GET", b"HEAD"):
                self._respond(writer, 405, "Method Not Allowed", "only GET\n")
            elif parts[1].split(b"?", 1)[0] != b"/metrics":
                self._respond(writer, 404, "Not Found", "try /metrics\n")
            else:
                self._respond(writer, 200, "OK", render(self._report()),
                              body=parts[0] == b"GET")
            with contextlib.suppress(ConnectionError):
                await writer.drain()
        finally:
            writer.close()

    @staticmethod
    def _respond(writer: asyncio.StreamWriter, code: int, reason: str, text: str,
                 body: bool = True) -> None:
        data = text.encode()
        head = (f"HTTP/1.1 {code} {reason}\r\nContent-Type: {CONTENT_TYPE}\r\n"
                f"Content-Length: {len(data)}\r\nConnection: close\r\n\r\n")
        writer.write(head.encode() + (data if body else b""))

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
            self._server = None
