"""What every session of one server shares, handed to each at creation instead of globals.

One object per running server, so two servers in one process (tests, ``ServerThread`` next to
a CLI server) never see each other's settings, counters or keys.
"""

from __future__ import annotations

import asyncio
import logging
import ssl
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from rlbridge.adapters.base import MiddlewareAdapter
from rlbridge.server.access import AllowList, KeyStore
from rlbridge.server.authz import Access
from rlbridge.server.config import ServerConfig
from rlbridge.server.flow import FlowTable
from rlbridge.server.handoff import LoopHandoff
from rlbridge.server.ledger import Ledger
from rlbridge.server.notices import Notices
from rlbridge.wire import PacketCodec


@dataclass
class ServerContext:
    """What every session shares: settings, middleware, codec, the loop and its hand-off."""

    config: ServerConfig
    adapter: MiddlewareAdapter
    codec: PacketCodec
    loop: asyncio.AbstractEventLoop
    handoff: LoopHandoff
    udp_transport: asyncio.DatagramTransport | None = None
    counters: dict[str, int] = field(default_factory=dict)
    keys: KeyStore | None = None
    #: TCP connections still in their hello/handshake (no session yet): closed at shutdown.
    handshaking: set[asyncio.BaseTransport] = field(default_factory=set)
    allow: AllowList = field(default_factory=lambda: AllowList(()))
    #: Who may publish and subscribe to what, and see whose Stats (server/authz.py).
    access: Access = field(default_factory=Access)
    #: TLS on the TCP listener (``--tls-cert``): every connection runs it (server/tls_side.py).
    tls: ssl.SSLContext | None = None
    #: Server totals and every session's counters (set by the registry; see ``Stats``).
    report: Callable[[], dict[str, Any]] | None = None
    #: Rate-limited warnings for the operator: wrong keys, malformed packets, refusals.
    notices: Notices = field(
        default_factory=lambda: Notices(logging.getLogger("rlbridge.server")))
    #: Counters of closed sessions and channels by client and topic (the metrics' labels).
    ledger: Ledger = field(default_factory=Ledger)
    #: Flow-controlled bindings by topic (server/flow.py): credit crosses sessions here.
    flows: FlowTable = field(default_factory=FlowTable)
    #: Threads for blocking middleware work: service calls (server/services.py).
    workers: ThreadPoolExecutor = field(default_factory=lambda: ThreadPoolExecutor(
        max_workers=32, thread_name_prefix="server-call"))

    def count(self, name: str, n: int = 1) -> None:
        """Add ``n`` to the server counter ``name`` (reported in ``Stats``)."""
        self.counters[name] = self.counters.get(name, 0) + n
