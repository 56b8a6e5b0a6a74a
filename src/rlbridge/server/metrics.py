"""An optional monitoring endpoint: ``/metrics`` (Prometheus), ``/healthz`` and ``/status`` (JSON).

* ``GET /metrics``: the counters in the text exposition format, with HELP, base units and
  bounded labels (:mod:`~rlbridge.server.exposition`).
* ``GET /healthz``: ``200 ok`` while the server accepts sessions, ``503`` while it shuts down
  (for a container healthcheck or a load balancer).
* ``GET /status``: a JSON document a person or a program can read, like NATS' ``/varz`` and
  ``/connz`` in one: the server's totals and uptime, and every open session with its link
  state, round-trip time and channels (each with its counters and link health). Same layout as
  the ``Stats`` reply (docs/protocol.md 13.2), plus ``uptime_seconds`` and ``accepting``.

It is served by the server's own asyncio loop, so a request reads the live counters on the
thread that owns them, with no lock and no copy across threads. ``prometheus_client`` was not
used: its HTTP server runs on a thread of its own, which would have to read session state owned
by the loop (or hop into it per scrape), and its metric objects would duplicate counters the
sessions keep anyway. The responder is deliberately tiny: one request per connection, a bounded
request head, a deadline on reading it, then the connection is closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from typing import TYPE_CHECKING, Any

from rlbridge.server.exposition import CONTENT_TYPE, render

if TYPE_CHECKING:
    from rlbridge.server.registry import SessionRegistry

log = logging.getLogger("rlbridge.server")

#: Longest request head accepted, and how long a client may take to send it.
MAX_REQUEST = 8192
REQUEST_TIMEOUT_S = 5.0
JSON_TYPE = "application/json"
TEXT_TYPE = "text/plain; charset=utf-8"
PATHS = (b"/metrics", b"/healthz", b"/status")


class MetricsEndpoint:
    """The listening socket and its handler; ``close`` is called by the server's shutdown."""

    def __init__(self, registry: SessionRegistry) -> None:
        self._registry = registry
        self._started = time.monotonic()
        self._server: asyncio.Server | None = None

    @property
    def port(self) -> int:
        assert self._server is not None, "metrics endpoint not started"
        port: int = self._server.sockets[0].getsockname()[1]
        return port

    async def start(self, host: str, port: int) -> MetricsEndpoint:
        self._server = await asyncio.start_server(self._handle, host, port, limit=MAX_REQUEST,
                                                  reuse_address=True)
        log.info("metrics on http://%s:%d/metrics (also /healthz, /status)", host, self.port)
        return self

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            try:
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), REQUEST_TIMEOUT_S)
            except (asyncio.IncompleteReadError, asyncio.LimitOverrunError,
                    asyncio.TimeoutError):
                self._respond(writer, 400, "Bad Request", "bad or incomplete request\n")
                return
            parts = head.split(b"\r\n", 1)[0].split()
            if len(parts) != 3 or not parts[2].startswith(b"HTTP/"):
                self._respond(writer, 400, "Bad Request", "bad request line\n")
            elif parts[0] not in (b"GET", b"HEAD"):
                self._respond(writer, 405, "Method Not Allowed", "only GET\n")
            elif (path := parts[1].split(b"?", 1)[0]) not in PATHS:
                self._respond(writer, 404, "Not Found", "try /metrics, /healthz or /status\n")
            else:
                code, reason, ctype, text = self._answer(path)
                self._respond(writer, code, reason, text, body=parts[0] == b"GET", ctype=ctype)
            with contextlib.suppress(ConnectionError):
                await writer.drain()
        finally:
            writer.close()

    def _answer(self, path: bytes) -> tuple[int, str, str, str]:
        """Status code, reason, content type and body of a known path."""
        registry = self._registry
        if path == b"/metrics":
            return 200, "OK", CONTENT_TYPE, render(registry.stats(), registry.ctx.ledger)
        if path == b"/healthz":
            if registry.accepting:
                return 200, "OK", TEXT_TYPE, "ok\n"
            return 503, "Service Unavailable", TEXT_TYPE, "shutting down\n"
        status: dict[str, Any] = {"accepting": registry.accepting,
                                  "uptime_seconds": round(time.monotonic() - self._started, 3),
                                  **registry.stats()}
        return 200, "OK", JSON_TYPE, json.dumps(status, indent=1) + "\n"

    @staticmethod
    def _respond(writer: asyncio.StreamWriter, code: int, reason: str, text: str,
                 body: bool = True, ctype: str = TEXT_TYPE) -> None:
        data = text.encode()
        head = (f"HTTP/1.1 {code} {reason}\r\nContent-Type: {ctype}\r\n"
                f"Content-Length: {len(data)}\r\nConnection: close\r\n\r\n")
        writer.write(head.encode() + (data if body else b""))

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(asyncio.TimeoutError):  # not the builtin on 3.10
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
            self._server = None
