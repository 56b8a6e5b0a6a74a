"""``Bridge``: the client SDK's front door, a small facade over its parts.

``connect`` opens a :class:`~rlbridge.csp.connection.Connection` (sockets, receive thread,
watchdog) and a :class:`~rlbridge.csp.sender.SendLoop` (send thread); ``subscribe`` and
``publish`` bind topics at run time and return CSP channels; after ``connect`` the caller's
thread only moves values through ring buffers. With ``reconnect`` a
:class:`~rlbridge.csp.reconnect.ReconnectSupervisor` opens a new session when one ends and
binds every channel again under its old id (docs/reliability.md).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import ssl
import sys
import threading
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from rlbridge.csp.auth import resolve_key
from rlbridge.csp.bridge_channels import IncomingChannel, OutgoingChannel
from rlbridge.csp.bridge_services import ServiceMethods
from rlbridge.csp.bridge_status import BridgeStatus
from rlbridge.csp.channel import _MISSING
from rlbridge.csp.connection import Connection, ConnectionClosed, Control
from rlbridge.csp.failsafe import GuardedChannel, OnLost, fail_safe
from rlbridge.csp.feedback import Feedback
from rlbridge.csp.idle import IdleSpec, idle_pair
from rlbridge.csp.io_priority import IoPriority
from rlbridge.csp.link_events import LinkEvents
from rlbridge.csp.reconnect import Backoff, ReconnectSupervisor
from rlbridge.csp.sender import SendLoop
from rlbridge.tls import client_tls
from rlbridge.wire import RemoteError, TopicClose, TopicConnect
from rlbridge.wire.packets import Durability, Reliability

log = logging.getLogger("rlbridge.client")

Transport = Literal["tcp", "udp"]
"""Per channel: ``udp`` when the newest value matters most, ``tcp`` when every value must arrive."""

DEFAULT_SWITCH_INTERVAL: float | None = None
"""``Bridge.connect`` leaves the process-wide GIL switch interval alone by default: the HRT loop
holds a short one while it runs (``rlbridge.csp.gil``); measured in docs/gil.md."""


class Bridge(BridgeStatus, ServiceMethods):
    """A session with a bridge server. Thread-safe for SRT code; see the module docstring."""

    def __init__(self, conn: Connection, send_loop: SendLoop,
                 backoff: Backoff | None = None) -> None:
        self._conn = conn
        self._sender = send_loop
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._incoming: dict[int, IncomingChannel] = {}
        self._outgoing: dict[int, OutgoingChannel] = {}
        self._events = LinkEvents(conn.link_state)
        self._feedback = Feedback(self._outgoing, self._events, send_loop.doorbell)
        self._io_priority = IoPriority(self._io_thread_ids)
        self._supervisor = None if backoff is None else ReconnectSupervisor(
            conn, backoff, self._bind_again)
        conn.keep_alive = self._supervisor is not None
        conn.on_values = self._on_values
        conn.on_ros_loss = self._on_ros_loss
        conn.link_report.on_change = self._events.emit
        conn.on_session_end = self._on_session_end
        conn.on_credit = self._feedback.on_credit
        conn.on_loss = self._feedback.on_loss

    @classmethod
    def connect(
        cls,
        host: str = "127.0.0.1",
        port: int = 7411,
        *,
        nodelay: bool = False,
        name: str | None = None,
        control: Control = "tcp",
        send_rate_hz: float | None = None,
        timeout: float = 5.0,
        switch_interval: float | None = DEFAULT_SWITCH_INTERVAL,
        reconnect: bool | Backoff = True,
        psk: bytes | str | None = None,
        psk_file: str | Path | None = None,
        bundles: bool = True,
        idle: IdleSpec | tuple[IdleSpec, IdleSpec] = "park",
        tls: bool | ssl.SSLContext = False,
        ca: str | Path | None = None,
        fingerprint: str | None = None,
        client_cert: tuple[str | Path, str | Path] | None = None,
    ) -> Bridge:
        """Open a session. ``control="udp"`` for a server started with ``--no-tcp``.

        ``reconnect``: when the session ends (server restart, outage seen by the watchdog),
        open a new one with backoff and bind every channel again. ``True``: the
        :class:`~rlbridge.csp.reconnect.Backoff` defaults (50 ms doubling to 2 s), or pass a
        ``Backoff``; ``False`` ends the bridge with its first session (channels close, blocked
        readers get ``ChannelClosed``). A failed first connect raises ``ConnectionFailed``.

        ``send_rate_hz`` starts the SDK's send loop: buffered values go out at that rate
        without anyone calling :meth:`send` (thesis figure 5.10). ``nodelay``: no Nagle on this
        client's socket. ``switch_interval`` shortens CPython's GIL switch interval (5 ms by
        default; ``None``: left alone), never lengthens it: a control loop waking while another
        thread computes waits at most that long for the GIL (docs/gil.md). Security
        (docs/security.md): the key is ``psk`` (hex), else ``psk_file``, else
        ``$RLBRIDGE_PSK``; TLS is ``tls=True``, ``ca=``, ``fingerprint=`` (pin) or an
        ``ssl.SSLContext``; ``client_cert=(cert, key)`` for mutual TLS.
        ``bundles=False``: a datagram per UDP channel, not a bundle per round (protocol.md 6.16).
        ``idle``: how the send and receive threads (and reads) wait (:mod:`rlbridge.csp.idle`):
        ``"park"`` (in the kernel), ``"spin"`` (poll 20 us, yield 200 us, park), ``"busy"`` (poll
        and yield), an ``IdleStrategy`` or a ``(send, receive)`` pair; costs: docs/concepts.md.
        """
        send_idle, receive_idle = idle_pair(idle)
        if switch_interval is not None and sys.getswitchinterval() > switch_interval:
            sys.setswitchinterval(switch_interval)
        name = name or f"rlbridge-{os.getpid()}"
        key = resolve_key(psk, psk_file, name=name)  # before any socket: a bad key leaks nothing
        secure = client_tls(tls, ca=ca, fingerprint=fingerprint, client_cert=client_cert)
        conn = Connection(host, port, name=name, nodelay=nodelay, control=control, timeout=timeout,
                          bundles=bundles)
        conn.psk, conn.tls, conn.idle = key, secure, receive_idle
        ack = conn.open()
        try:
            sender = SendLoop(conn, rate_hz=send_rate_hz, max_batch=ack.limits.max_batch,
                              idle=send_idle)
        except BaseException:
            conn.close()  # e.g. a bad send rate: do not leak the session and its thread
            raise
        backoff = reconnect if isinstance(reconnect, Backoff) else Backoff() if reconnect else None
        bridge = cls(conn, sender, backoff)
        sender.start()
        if bridge._supervisor is not None:
            bridge._supervisor.start()
        return bridge

    # -- channels --------------------------------------------------------------------------
    def subscribe(
        self,
        topic: str,
        msg_type: str,
        field: str | None = "data",
        *,
        transport: Transport = "udp",
        blocking: bool = False,
        buffer_size: int = 1,
        initial: Any = _MISSING,
        redundancy: int = 0,
        latest: bool = False,
        max_age_ms: int = 0,
        reliability: Reliability | None = None,
        depth: int = 10,
        durability: Durability = "volatile",
        on_lost: OnLost = "hold",
        flow: bool | None = None,
    ) -> IncomingChannel:
        """A channel of the values published on ``topic`` (``field=None``: whole messages).

        Policies (docs/policies.md): ``redundancy=k`` (UDP) repeats the previous k values in
        each datagram; ``latest=True`` delivers the newest value instead of a backlog;
        ``max_age_ms`` drops values older than that on arrival (``health().expired``).
        ``reliability`` (``"reliable"`` / ``"best_effort"``), ``depth`` and ``durability``
        are the middleware QoS of the server's subscription (ROS 2); ``reliability=None``
        picks by transport (best effort for UDP, reliable for TCP); ``durability=
        "transient_local"`` receives a latched topic's last values, ``"match"`` copies the
        QoS of the topic's publishers (as ``ros2 topic echo`` does).

        Non-blocking channels return the latest value on every read (or ``initial`` before the
        first one; with neither, ``NoValueYet``); blocking channels wait for a new value.
        Raises the server's reason (``UnknownTypeError``, ``NoSuchFieldError``,
        ``TypeClashError``) if the binding is refused. ``on_lost`` is what reads do while the
        link is lost: ``"hold"``, ``SafeValue(v)`` or ``"raise"`` (:mod:`rlbridge.csp.failsafe`).
        ``flow``: credit flow control, every value end to end at the reader's pace (default:
        on for blocking TCP channels that are not ``latest``; docs/policies.md).
        """
        flow = _flow(flow, transport, latest, blocking)
        guard = fail_safe(on_lost, self._events)
        if buffer_size < 1:
            raise ValueError(
                f"an incoming channel needs buffer_size >= 1 (got {buffer_size}): values "
                "arrive from the network whether or not a reader waits")
        ch_id = next(self._ids)
        kind = IncomingChannel if guard is None else GuardedChannel
        channel = kind(ch_id, topic, msg_type, field, transport=transport, blocking=blocking,
                       buffer_size=buffer_size, initial=initial if not blocking else _MISSING,
                       latest=latest, max_age_ms=max_age_ms, link=self._conn.link,
                       credit_bell=self._sender.doorbell if flow else None)
        if isinstance(channel, GuardedChannel):
            channel.failsafe = guard
        channel.read_idle = self._conn.idle  # blocking reads wait as the receive thread does
        with self._lock:
            self._incoming[ch_id] = channel
        try:
            ack = self._conn.request_topic(TopicConnect(
                ch_id, "subscribe", topic, msg_type, field, transport, buffer_size,
                max_age_ms=max_age_ms, redundancy=redundancy, latest=latest,
                reliability=reliability, depth=depth, flow=flow, durability=durability))
        except BaseException:
            with self._lock:
                self._incoming.pop(ch_id, None)
            raise
        channel.msg_type = ack.msg_type
        if flow:
            self._sender.add_credit(channel)
        return channel

    def publish(
        self,
        topic: str,
        msg_type: str,
        field: str | None = "data",
        *,
        transport: Transport = "udp",
        through_buffer: bool = False,
        buffer_size: int = 1024,
        redundancy: int = 0,
        latest: bool = False,
        max_age_ms: int = 0,
        reliability: Reliability | None = None,
        depth: int = 10,
        durability: Durability = "volatile",
        max_rate_hz: float | None = None,
        adapt_rate: bool = False,
        flow: bool | None = None,
    ) -> OutgoingChannel:
        """A channel whose values are published on ``topic``.

        ``through_buffer=False``: each ``write`` hands the value to the send thread at once.
        ``through_buffer=True``: values wait in the channel until :meth:`send` or the send loop.
        Either way ``write`` never blocks and never touches a socket; a full buffer drops its
        oldest value and counts it (``statistics().overwritten``). Policies as in
        :meth:`subscribe`; ``max_age_ms`` is enforced here before sending and by the server
        before publishing. ``reliability`` and ``depth``: the publisher's middleware QoS,
        as in :meth:`subscribe`. ``max_rate_hz`` lets at most that many values per second
        leave (the rest wait in the buffer); ``adapt_rate`` lowers it while the server
        reports first-hop loss and raises it back (``health().rate_limit_hz``). ``flow``:
        send only what the topic's subscribers have room for (default: on for TCP channels
        that are not ``latest``; ``wait_writable()`` then paces a writer that must lose
        nothing). docs/policies.md says what each promises. ``durability``
        (``transient_local``: a latched topic, its last ``depth`` values kept for late
        subscribers) is the publisher's middleware durability, as in :meth:`subscribe`.
        """
        flow = _flow(flow, transport, latest, True)
        ch_id = next(self._ids)
        channel = OutgoingChannel(ch_id, topic, msg_type, field, transport=transport,
                                  immediate=not through_buffer, buffer_size=buffer_size,
                                  doorbell=self._sender.doorbell, redundancy=redundancy,
                                  latest=latest, max_age_ms=max_age_ms, link=self._conn.link,
                                  max_rate_hz=max_rate_hz, adapt_rate=adapt_rate, flow=flow)
        ack = self._conn.request_topic(TopicConnect(
            ch_id, "publish", topic, msg_type, field, transport, buffer_size,
            max_age_ms=max_age_ms, redundancy=redundancy, latest=latest,
            reliability=reliability, depth=depth, flow=flow, loss_report=True,
            durability=durability))
        channel.bound(ack)
        with self._lock:
            self._outgoing[ch_id] = channel
        self._sender.add(channel)
        return channel

    def send(self, wait: bool = False, *, inline: bool = False) -> None:
        """Flush every buffered outgoing value (thesis: ``send``); blocks only if ``wait``.

        ``wait=True`` returns once the send thread has handed them to the sockets, and no value
        waits for credit or a rate limit any more (at most 5 s). ``inline=True`` (SRT code only):
        this thread sends a plain UDP round itself when it can. Costs, promises: docs/concepts.md.
        """
        if self._conn.closed.is_set():
            raise ConnectionClosed(f"bridge is closed: {self._conn.close_reason}")
        if not (inline and self._sender.send_inline()):  # inline: in the kernel already
            self._sender.flush(wait=wait)

    def unsubscribe(self, channel: IncomingChannel | OutgoingChannel) -> None:
        """Unbind one channel on the server and close it here."""
        with self._lock:
            self._incoming.pop(channel.channel_id, None)
            out = self._outgoing.pop(channel.channel_id, None)
        if out is not None:
            self._sender.remove(out)
        if isinstance(channel, IncomingChannel):
            self._sender.remove_credit(channel)
        channel.close()
        self._conn.forget_topic(channel.channel_id)
        if self._conn.up:  # while reconnecting: the new session does not bind it again
            with contextlib.suppress(OSError, ConnectionClosed):
                self._conn.send_control(TopicClose(channel.channel_id))

    def set_io_priority(self, priority: int = 40) -> bool:
        """Run the SDK's I/O threads at ``SCHED_FIFO`` ``priority``, below the loop (50).

        A thread preempted while it holds the GIL keeps an in-process loop waiting whatever
        its priority (docs/gil.md). Needs ``CAP_SYS_NICE``; ``False`` and one
        ``RealTimeWarning`` when refused. Opt-in: a real-time thread that spins can starve
        the machine. Later sessions' threads (after a reconnect) get the same priority.
        """
        return self._io_priority.request(priority)

    def _io_thread_ids(self) -> list[int | None]:
        supervisor = self._supervisor
        return [self._conn.receive_thread_id, self._sender.native_id,
                None if supervisor is None else supervisor.native_id]

    @property
    def send_rate_hz(self) -> float | None:
        """Rate of the SDK's send loop (``Bridge.connect(send_rate_hz=...)``), or ``None``."""
        return self._sender.rate_hz

    def _on_values(self, ch: int, first_seq: int, stamps: list[int], values: list[Any]) -> None:
        channel = self._incoming.get(ch)
        if channel is not None:
            channel.deliver(first_seq, stamps, values)

    # -- sessions --------------------------------------------------------------------------
    def _on_session_end(self, reason: str, final: bool) -> None:
        """A session ended: hold outgoing values; for good, close every channel."""
        self._sender.pause()
        if final:
            self._close_channels()

    def _bind_again(self) -> None:
        """Supervisor thread, new session: bind every channel under its old id, then resume.

        A binding the server now refuses (a type clash with a newer publisher) closes that
        channel and says why in the log; a lost session raises and the supervisor tries again.
        """
        for req in self._conn.bindings():
            incoming = self._incoming.get(req.channel)
            outgoing = self._outgoing.get(req.channel)
            if incoming is not None:
                incoming.restart_sequence()  # before the request: values may follow at once
                incoming.relink(self._conn.link)
            elif outgoing is not None:
                outgoing.relink(self._conn.link)
                outgoing.restart_sequence()  # the new binding numbers (and credits) from 0
            try:
                credit = self._conn.request_topic(req).credit
                if outgoing is not None and credit is not None:
                    outgoing.on_credit(credit)
            except RemoteError as exc:
                name = req.topic if isinstance(req, TopicConnect) else getattr(req, "service", "")
                log.warning("channel %d (%s) not bound again: %s", req.channel, name, exc)
                with self._lock:
                    # Not ``a or b``: an empty channel is falsy (``len`` is its buffered count).
                    channel: IncomingChannel | OutgoingChannel | None = self._incoming.pop(
                        req.channel, None)
                    if channel is None:
                        channel = self._outgoing.pop(req.channel, None)
                self._conn.forget_topic(req.channel)
                if channel is not None:
                    channel.close()
        self._io_priority.reapply()
        self._sender.resume()
        ack = self._conn.ack
        self._conn.link_report.restored(f"reconnected: session {ack.session if ack else '?'}")

    # -- lifetime --------------------------------------------------------------------------
    def close(self) -> None:
        """Flush, say goodbye, stop every SDK thread, close every channel; idempotent.

        Prompt in every phase: a reconnect backoff ends at once and a handshake is aborted.
        """
        if self._supervisor is not None:
            self._supervisor.request_stop()
        self._sender.close()
        self._conn.close()
        if self._supervisor is not None:
            self._supervisor.stop()
        self._close_channels()
        self._events.close()

    def _close_channels(self) -> None:
        with self._lock:
            channels: list[IncomingChannel | OutgoingChannel] = [
                *self._incoming.values(), *self._outgoing.values()]
            self._incoming.clear()
            self._outgoing.clear()
        for channel in channels:
            channel.close()

    def __enter__(self) -> Bridge:
        return self

    def __exit__(self, et: type[BaseException] | None, e: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def _flow(flow: bool | None, transport: Transport, latest: bool, blocking: bool) -> bool:
    """Whether a channel is flow-controlled: asked for, else TCP every-value by default."""
    promises_every_value = transport == "tcp" and not latest
    if flow is None:
        return promises_every_value and blocking
    if flow and not promises_every_value:
        raise ValueError("flow control needs a TCP channel that is not latest: UDP and "
                         "latest channels drop instead of waiting (docs/policies.md)")
    return flow
