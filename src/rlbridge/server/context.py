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

#: Every server event counter (``ServerContext.count``), present at 0 from the start: in
#: ``Stats`` and on /metrics a counter that appeared only at its first increment has no
#: baseline, so a rate or an alert on it (``increase(rlbridge_udp_bad_mac_total[5m])``) sees
#: nothing until the second event.
EVENT_COUNTERS = (
    # sessions and their handshakes
    "sessions_opened", "sessions_authenticated", "sessions_timed_out", "handshake_timeouts",
    "auth_failed", "not_allowed", "topic_not_allowed",
    # TLS
    "tls_sessions", "tls_failed", "tls_plaintext_clients",
    # what arrived and could not be used
    "malformed", "errors_sent", "tcp_rejected_records", "dropped_unknown_channel",
    "rate_dropped",
    # UDP: datagrams outside a session, sealed datagrams that do not open, and control packets
    # too large to send (server/datagram_limit.py)
    "udp_no_token", "udp_bad_token", "udp_malformed", "udp_too_large", "udp_not_allowed",
    "udp_too_large_out",
    "udp_hello_refused", "udp_unexpected_proof", "udp_handshakes_evicted",
    "udp_unsealed", "udp_bad_mac", "udp_replayed",
    # services and actions
    "service_calls", "goals_sent",
)


@dataclass
class ServerContext:
    """What every session shares: settings, middleware, codec, the loop and its hand-off."""

    config: ServerConfig
    adapter: MiddlewareAdapter
    codec: PacketCodec
    loop: asyncio.AbstractEventLoop
    handoff: LoopHandoff
    udp_transport: asyncio.DatagramTransport | None = None
    counters: dict[str, int] = field(default_factory=lambda: dict.fromkeys(EVENT_COUNTERS, 0))
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
        """Add ``n`` to the server counter ``name`` (reported in ``Stats``; one of
        :data:`EVENT_COUNTERS`, tests/server/test_event_counters.py checks the source)."""
        self.counters[name] = self.counters.get(name, 0) + n
