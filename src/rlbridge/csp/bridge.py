"""``Bridge``: the client SDK's front door, a small facade over its parts.

``Bridge.connect`` opens a :class:`~rlbridge.csp.connection.Connection` (sockets, receive
thread, watchdog) and a :class:`~rlbridge.csp.sender.SendLoop` (send thread). ``subscribe``
and ``publish`` bind a topic at run time (message type + field) and return CSP channels
(:mod:`rlbridge.csp.bridge_channels`). The caller's thread never touches a socket after
``connect``: reads and writes only move values through ring buffers.
"""

from __future__ import annotations

import itertools
import os
import sys
import threading
import warnings
from collections.abc import Callable
from types import TracebackType
from typing import Any, Literal

from rlbridge.csp.bridge_channels import IncomingChannel, OutgoingChannel
from rlbridge.csp.channel import _MISSING
from rlbridge.csp.connection import Connection, ConnectionClosed, Control
from rlbridge.csp.errors import RealTimeWarning
from rlbridge.csp.sender import SendLoop
from rlbridge.wire import TopicClose, TopicConnect
from rlbridge.wire.link import LinkState

Transport = Literal["tcp", "udp"]

DEFAULT_SWITCH_INTERVAL: float | None = None
"""``Bridge.connect`` leaves the process-wide GIL switch interval alone by default: the HRT loop
holds a short one while it runs (``rlbridge.csp.gil``); measured in docs/gil.md."""


class Bridge:
    """A session with a bridge server. Thread-safe for SRT code; see the module docstring."""

    def __init__(self, conn: Connection, send_loop: SendLoop) -> None:
        self._conn = conn
        self._sender = send_loop
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._incoming: dict[int, IncomingChannel] = {}
        self._outgoing: dict[int, OutgoingChannel] = {}
        self._link_callbacks: list[Callable[[LinkState], None]] = []
        conn.on_values = self._on_values
        conn.on_link_change = self._on_link_change

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
    ) -> Bridge:
        """Open a session. ``control="udp"`` for a server started with ``--no-tcp``.

        ``send_rate_hz`` starts the SDK's send loop: buffered values go out at that rate
        without anyone calling :meth:`send` (thesis figure 5.10). ``nodelay`` disables Nagle's
        algorithm on this client's TCP socket (the server has ``--nodelay`` for its side).
        ``switch_interval`` shortens CPython's process-wide GIL switch interval (5 ms by
        default) to this many seconds, never lengthens it: a control loop that wakes while
        another Python thread computes then waits at most that long for the GIL (docs/gil.md).
        ``None`` leaves the interpreter's setting alone.
        """
        if switch_interval is not None and sys.getswitchinterval() > switch_interval:
            sys.setswitchinterval(switch_interval)
        conn = Connection(host, port, name=name or f"rlbridge-{os.getpid()}", nodelay=nodelay,
                          control=control, timeout=timeout)
        ack = conn.open()
        try:
            sender = SendLoop(conn, rate_hz=send_rate_hz, max_batch=ack.limits.max_batch)
        except BaseException:
            conn.close()  # e.g. a bad send rate: do not leak the session and its thread
            raise
        bridge = cls(conn, sender)
        sender.start()
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
    ) -> IncomingChannel:
        """A channel of the values published on ``topic`` (``field=None``: whole messages).

        Non-blocking channels return the latest value on every read (or ``initial`` before the
        first one; with neither, ``NoValueYet``); blocking channels wait for a new value.
        Raises the server's reason (``UnknownTypeError``, ``NoSuchFieldError``,
        ``TypeClashError``) if the binding is refused.
        """
        if buffer_size < 1:
            raise ValueError(
                f"an incoming channel needs buffer_size >= 1 (got {buffer_size}): values "
                "arrive from the network whether or not a reader waits")
        ch_id = next(self._ids)
        channel = IncomingChannel(ch_id, topic, msg_type, field, transport=transport,
                                  blocking=blocking, buffer_size=buffer_size,
                                  initial=initial if not blocking else _MISSING)
        with self._lock:
            self._incoming[ch_id] = channel
        try:
            ack = self._conn.request_topic(TopicConnect(
                ch_id, "subscribe", topic, msg_type, field, transport, buffer_size,
                redundancy=redundancy))
        except BaseException:
            with self._lock:
                self._incoming.pop(ch_id, None)
            raise
        channel.msg_type = ack.msg_type
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
    ) -> OutgoingChannel:
        """A channel whose values are published on ``topic``.

        ``through_buffer=False``: each ``write`` hands the value to the send thread at once.
        ``through_buffer=True``: values wait in the channel until :meth:`send` or the send loop.
        Either way ``write`` never blocks and never touches a socket; a full buffer drops its
        oldest value and counts it (``statistics().overwritten``).
        """
        ch_id = next(self._ids)
        ack = self._conn.request_topic(TopicConnect(
            ch_id, "publish", topic, msg_type, field, transport, buffer_size,
            redundancy=redundancy))
        channel = OutgoingChannel(ch_id, topic, ack.msg_type, field, transport=transport,
                                  immediate=not through_buffer, buffer_size=buffer_size,
                                  doorbell=self._sender.doorbell)
        with self._lock:
            self._outgoing[ch_id] = channel
        self._sender.add(channel)
        return channel

    def send(self, wait: bool = False) -> None:
        """Flush every buffered outgoing value (thesis: ``send``); blocks only if ``wait``."""
        if self._conn.closed.is_set():
            raise ConnectionClosed(f"bridge is closed: {self._conn.close_reason}")
        self._sender.flush(wait=wait)

    def unsubscribe(self, channel: IncomingChannel | OutgoingChannel) -> None:
        """Unbind one channel on the server and close it here."""
        with self._lock:
            self._incoming.pop(channel.channel_id, None)
            out = self._outgoing.pop(channel.channel_id, None)
        if out is not None:
            self._sender.remove(out)
        channel.close()
        if not self._conn.closed.is_set():
            self._conn.send_control(TopicClose(channel.channel_id))

    def set_io_priority(self, priority: int = 40) -> bool:
        """Run the SDK's receive and send threads at ``SCHED_FIFO`` ``priority``.

        Put them below the control loop (``PriParallel`` gives it 50) and above everything
        else: a thread preempted by another process while it holds the GIL keeps the loop
        waiting whatever the loop's own priority (docs/gil.md measures it at 1 kHz traffic).
        Needs ``CAP_SYS_NICE``; returns ``False`` and says why in one ``RealTimeWarning`` when
        refused. Opt-in, because a real-time thread that spins can starve the machine.
        """
        threads = [self._conn._thread, self._sender._thread]
        try:
            for thread in threads:
                if thread is not None and thread.native_id is not None:
                    os.sched_setscheduler(thread.native_id, os.SCHED_FIFO,
                                          os.sched_param(priority))
        except (OSError, AttributeError) as exc:
            warnings.warn(RealTimeWarning(
                f"SDK threads stay at normal priority: SCHED_FIFO {priority} refused ({exc}); "
                "it needs CAP_SYS_NICE or RLIMIT_RTPRIO"), stacklevel=2)
            return False
        return True

    @property
    def send_rate_hz(self) -> float | None:
        """Rate of the SDK's send loop (``Bridge.connect(send_rate_hz=...)``), or ``None``."""
        return self._sender.rate_hz

    # -- link ------------------------------------------------------------------------------
    @property
    def link_state(self) -> LinkState:
        """``connected``, ``degraded`` or ``lost``: read it from control code, it never blocks."""
        return self._conn.link_state

    @property
    def closed(self) -> bool:
        """True once the session has ended: closed here, by the server, or the socket broke."""
        return self._conn.closed.is_set()

    @property
    def close_reason(self) -> str:
        """Why the session ended (``""`` while it is open)."""
        return self._conn.close_reason

    def on_link_change(self, callback: Callable[[LinkState], None]) -> None:
        """Call ``callback(state)`` from the receive thread when the link state changes."""
        self._link_callbacks.append(callback)

    @property
    def rtt_ns(self) -> int:
        """Smoothed round-trip time from heartbeats (-1 until measured)."""
        link = self._conn.link
        return -1 if link is None else link.stats(0).rtt_ns

    def server_stats(self) -> dict[str, Any]:
        """The server's counters for this session, its totals, and the topics it knows."""
        return dict(self._conn.request_stats())

    @property
    def session_id(self) -> int:
        assert self._conn.ack is not None
        return self._conn.ack.session

    def _on_values(self, ch: int, first_seq: int, stamps: list[int], values: list[Any]) -> None:
        channel = self._incoming.get(ch)
        if channel is not None:
            channel.deliver(first_seq, stamps, values)

    def _on_link_change(self, state: LinkState) -> None:
        for callback in self._link_callbacks:
            callback(state)

    # -- lifetime --------------------------------------------------------------------------
    def close(self) -> None:
        """Flush, say goodbye, stop both threads, close every channel; idempotent."""
        self._sender.close()
        self._conn.close()
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
