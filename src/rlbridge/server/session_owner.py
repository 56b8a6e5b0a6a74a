"""A session as its parts see it: what the watchdog, the topic-connects, the service calls and
the goals use of it.

:class:`~rlbridge.server.session.Session` routes packets and owns two parts: its watchdog
(:mod:`rlbridge.server.watchdog`) and the decisions about what may be connected and what an
accepted topic-connect binds (:mod:`rlbridge.server.connect`); value packets go to
:mod:`rlbridge.server.values_in`. The parts work on the session's state, so they need its type;
importing ``session`` for it made an import circle. They depend on this description instead,
imports run one way (``session`` -> parts -> ``session_owner``), and mypy checks that
``Session`` fits wherever it hands itself over.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from rlbridge.server.bindings import Inbound, Outbound
from rlbridge.server.context import ServerContext
from rlbridge.server.ratelimit import RateLimiter
from rlbridge.server.session_stats import ChannelTotals
from rlbridge.server.sinks import PacketSink, UdpSink
from rlbridge.wire import ErrorCode, LossReport, Packet
from rlbridge.wire.link import LinkMonitor

__all__ = ["SessionOwner"]


class SessionOwner(Protocol):
    """What the watchdog and the topic-connect decisions use of a session."""

    ctx: ServerContext
    link: LinkMonitor
    tcp: PacketSink | None
    udp: UdpSink | None
    #: Called once the client's UDP address is known (the sink exists), then forgotten.
    udp_waiters: list[Callable[[], None]]
    inbound: dict[int, Inbound]
    outbound: dict[int, Outbound]
    tcp_bytes_in: int
    closed: bool
    #: Who the client proved to be (authorization, server/authz.py), and its refusals.
    identity: str | None
    topics_refused: int
    #: ``--max-rate`` (None: no limit), and the totals of closed channels (server/values_in.py).
    rate: RateLimiter | None
    totals: ChannelTotals

    id: int
    name: str

    def close(self, reason: str, *, notify: bool = True) -> None: ...

    def send_control(self, packet: Packet, via: PacketSink | None = None) -> None: ...

    def error(self, code: ErrorCode, reason: str, channel: int | None = None,
              via: PacketSink | None = None, values: int = 0) -> None: ...

    def report_loss(self) -> None: ...

    def loss_reports(self) -> list[LossReport]: ...
