"""The connection as the parts of its session see it: what they read, set and call.

:class:`~rlbridge.client.session.connection.Connection` owns a session and builds its parts: the
handshake (:mod:`rlbridge.client.session.handshake`), the receive thread
(:mod:`rlbridge.client.session.receiver`)
and the requests waiting for answers (:mod:`rlbridge.client.session.pending`). The parts work on the
connection's state, so they need its type; importing ``connection`` for it made an import
circle. They depend on this description instead, imports run one way (``connection`` ->
parts -> ``session_owner``), and mypy checks that ``Connection`` fits wherever it hands itself
over. A part that needs more of the connection adds the member here.

Why a mirror and not ``from rlbridge.client.session.connection import Connection`` (even under
``TYPE_CHECKING``): ``connection`` imports every part that uses this (the handshake, the receive
thread, the pending requests, the service calls and through them the actions and TLS), so the
import would close a circle (tests/architecture/test_import_cycles.py counts type-only imports).
The mirror can go once building a session's parts moves out of ``Connection`` into a module
above both (issue 26's ``client/session/``).
"""

from __future__ import annotations

import collections
import socket
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Literal, Protocol

from rlbridge.client.session.link_report import LinkHandler, LinkReport
from rlbridge.wire import (
    ConnectAck,
    Error,
    GoalResult,
    LossReport,
    Packet,
    PacketCodec,
    ServiceRequest,
    ServiceResult,
    Stats,
    TopicAck,
    TopicError,
)
from rlbridge.wire.link import LinkMonitor

if TYPE_CHECKING:
    from rlbridge.client.session.auth import ClientAuth
    from rlbridge.client.session.stream_guard import StreamGuard
    from rlbridge.csp.idle import IdleStrategy
    from rlbridge.tls import ClientTls

__all__ = ["Answers", "Control", "LinkHandler", "ServiceAnswers", "SessionOwner",
           "ValuesHandler"]

#: The transport of the control packets (hello, topic-connect, stats requests).
Control = Literal["tcp", "udp"]
#: ``(channel, first_seq, stamps, values)``: how the receive thread hands values to channels.
ValuesHandler = Callable[[int, int, list[int], list[object]], None]


class Answers(Protocol):
    """Where the receive thread hands the answers to control requests."""

    #: Bindings that bring values or requests in (subscriptions, service offers).
    incoming: int

    def answer(self, packet: TopicAck | TopicError) -> None: ...

    def answer_stats(self, packet: Stats) -> None: ...

    def refused(self, error: Error) -> None: ...


class ServiceAnswers(Protocol):
    """Where the receive thread hands service results, requests and goal results."""

    def on_result(self, packet: ServiceResult) -> None: ...

    def on_request(self, packet: ServiceRequest) -> None: ...

    def on_goal_result(self, packet: GoalResult) -> None: ...

    @property
    def waiting(self) -> bool:
        """A service call or a goal waits for its answer."""
        ...


class SessionOwner(Protocol):
    """What the handshake, the receive thread and the pending requests use of a connection."""

    # -- set up by the connection, read by the parts
    host: str
    port: int
    nodelay: bool
    control: Control
    timeout: float
    codec: PacketCodec
    #: Flags of every datagram (``FLAG_BUNDLES`` unless bundles are off).
    udp_flags: int
    keep_alive: bool
    closed: threading.Event
    close_reason: str
    # -- the session's sockets (the handshake opens them)
    tcp: socket.socket | None
    udp: socket.socket | None
    tcp_bytes_out: int
    tcp_lock: threading.Lock
    # -- the session's state (the receive thread reads and counts)
    datagrams_dropped: collections.Counter[str]
    #: The link as told to the owner (the receive thread reports its watchdog there).
    link_report: LinkReport
    #: How the receive thread waits for a readable socket.
    idle: IdleStrategy

    @property
    def auth(self) -> ClientAuth | None: ...

    @property
    def tls(self) -> ClientTls | None: ...

    @property
    def guard(self) -> StreamGuard: ...

    @property
    def ack(self) -> ConnectAck | None: ...

    @property
    def link(self) -> LinkMonitor | None: ...

    @property
    def on_values(self) -> ValuesHandler | None: ...

    @property
    def on_error(self) -> Callable[[Error], None] | None: ...

    @property
    def on_credit(self) -> Callable[[int, int], None] | None: ...

    @property
    def on_loss(self) -> Callable[[LossReport], None] | None: ...

    @property
    def requests(self) -> Answers: ...

    @property
    def services(self) -> ServiceAnswers: ...

    @property
    def on_ros_loss(self) -> Callable[[int, int], None] | None: ...

    @property
    def generation(self) -> int: ...

    @property
    def up(self) -> bool: ...

    def wait_up(self, timeout: float) -> bool: ...

    def send_control(self, packet: Packet) -> None: ...

    def send_tcp(self, data: bytes | bytearray) -> None: ...

    def tcp_received(self, data: bytes) -> bytes: ...

    def send_udp_packet(self, packet: Packet) -> None: ...

    def end_session(self, reason: str, generation: int) -> None: ...
