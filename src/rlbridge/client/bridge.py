"""``Bridge``: the client SDK's front door, a small facade over its parts.

``connect`` opens a :class:`~rlbridge.client.session.connection.Connection` (sockets, receive
thread, watchdog) and a :class:`~rlbridge.client.session.sender.SendLoop` (send thread);
``subscribe`` and ``publish`` bind topics at run time and return CSP channels; after
``connect`` the caller's thread only moves values through ring buffers. With ``reconnect`` a
:class:`~rlbridge.client.session.reconnect.ReconnectSupervisor` opens a new session when one
ends and binds every channel again under its old id (docs/reliability.md).

One facade, in sections: channels, the session's status (link state, counters; none of these
blocks except ``server_stats``), the server's requests (services, actions, parameters: calls
from a soft-real-time thread that may block; a loop uses :meth:`Bridge.service_client`,
:mod:`rlbridge.client.service_client`), and the session's lifetime.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import sys
import threading
from collections.abc import Callable
from types import TracebackType
from typing import Any

import msgspec

from rlbridge.adapters.base import QoS
from rlbridge.client.channels.failsafe import GuardedChannel, fail_safe
from rlbridge.client.channels.incoming import IncomingChannel, OutgoingChannel
from rlbridge.client.option_rules import check_connect, check_publish, check_subscribe
from rlbridge.client.options import Policy, Psk, Tls, Transport, Tuning
from rlbridge.client.service_client import DEFAULT_TIMEOUT, ServiceClient
from rlbridge.client.session import parameters
from rlbridge.client.session.actions import Goal
from rlbridge.client.session.auth import resolve_key
from rlbridge.client.session.connection import Connection
from rlbridge.client.session.feedback import Feedback
from rlbridge.client.session.goodbye import Goodbye, deliver_last
from rlbridge.client.session.io_priority import IoPriority
from rlbridge.client.session.link_events import DEFAULT_EVENT_BUFFER, LinkEvent, LinkEvents
from rlbridge.client.session.reconnect import Backoff, ClientState, ReconnectSupervisor
from rlbridge.client.session.sender import SendLoop
from rlbridge.client.session.services import ServiceRequests
from rlbridge.csp.channel import _MISSING, Channel
from rlbridge.csp.idle import idle_pair
from rlbridge.errors import ConnectionClosed, ParameterError, RemoteError
from rlbridge.tls import client_tls
from rlbridge.wire import GoalSend, ServiceOffer, TopicClose, TopicConnect
from rlbridge.wire.link import LinkState

log = logging.getLogger("rlbridge.client")

_DEFAULT_QOS = QoS()
_DEFAULT_POLICY = Policy()
_DEFAULT_TUNING = Tuning()


class Bridge:
    """A session with a bridge server, and the channels bound through it.

    ::

        with Bridge.connect("127.0.0.1", 7411) as bridge:
            cmd = bridge.subscribe("/cmd", "std_msgs/msg/Float64",
                                   policy=Policy.setpoint(max_age_ms=50,
                                                          on_lost=SafeValue(0.0)))
            out = bridge.publish("/angle", "std_msgs/msg/Float64")
            out.write(cmd.read())   # never blocks: the SDK's threads do the network

    After ``connect`` the caller's thread only moves values through ring buffers; the SDK's
    send and receive threads (and, with ``reconnect``, a supervisor) do the rest. Methods
    are thread-safe; each channel has one writer and one reader thread at a time.
    """

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
        name: str | None = None,
        security: Psk | Tls | None = None,
        reconnect: bool | Backoff = True,
        nodelay: bool = False,
        send_rate_hz: float | None = None,
        timeout: float = 5.0,
        tuning: Tuning = _DEFAULT_TUNING,
    ) -> Bridge:
        """Open a session with the bridge server at ``host:port`` (``rlbridge serve``).

        ``name`` identifies this client to the server (its logs, key file, topic rules;
        default ``rlbridge-<pid>``). ``security``: ``Psk(key=...)`` or ``Psk(file=...)`` to
        authenticate with a pre-shared key (every datagram and the TCP stream sealed),
        ``Tls(...)`` for TLS 1.3 (with ``Tls(psk=...)`` a key as well), ``None``: the key in
        ``$RLBRIDGE_PSK`` if set, else plaintext (docs/security.md).

        ``reconnect``: when the session ends (server restart, outage seen by the watchdog),
        open a new one with backoff and bind every channel again. ``True``: the
        :class:`Backoff` defaults (50 ms doubling to 2 s), or pass a ``Backoff``; ``False``
        ends the bridge with its first session (channels close, blocked readers get
        :class:`ChannelClosed`). A failed first connect raises :class:`ConnectionFailed`.

        ``nodelay``: no Nagle on this client's TCP socket. ``send_rate_hz`` starts the SDK's
        send loop: buffered values (``through_buffer=True``) go out at that rate without anyone
        calling :meth:`send` (thesis figure 5.10). ``timeout``: seconds for the handshake and
        each binding, and at most for :meth:`close` to see its last values taken. ``tuning``:
        the rarely touched knobs (:class:`Tuning`). Options that cannot take effect together
        raise ``ValueError`` before any socket is opened.
        """
        check_connect(security, reconnect, tuning, nodelay=nodelay, timeout=timeout,
                      send_rate_hz=send_rate_hz)
        send_idle, receive_idle = idle_pair(tuning.idle)
        name = name or f"rlbridge-{os.getpid()}"
        psk = security.psk if isinstance(security, Tls) else security
        key = resolve_key(psk.key if psk else None, psk.file if psk else None,
                          name=name)  # before any socket: a bad key leaks nothing
        secure = None if not isinstance(security, Tls) else client_tls(
            security.context or True, ca=security.ca, fingerprint=security.fingerprint,
            client_cert=security.client_cert)
        interval = tuning.switch_interval
        if interval is not None and sys.getswitchinterval() > interval:
            sys.setswitchinterval(interval)
        conn = Connection(host, port, name=name, nodelay=nodelay, control=tuning.control,
                          timeout=timeout, bundles=tuning.bundles)
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
        qos: QoS = _DEFAULT_QOS,
        policy: Policy = _DEFAULT_POLICY,
        blocking: bool = False,
        buffer_size: int = 1,
        initial: Any = _MISSING,
    ) -> IncomingChannel:
        """A channel of the values published on ``topic`` (``field=None``: whole messages).

        ``transport``: ``"udp"`` when the newest value matters most, ``"tcp"`` when every
        value must arrive. ``qos``: the middleware side of the server's subscription
        (:class:`QoS`; reliability by transport unless given). ``policy``: what the network
        does with the values (:class:`Policy`: latest, age limit, redundancy, flow control,
        fail-safe on a lost link).

        ``blocking=False`` (the hard-real-time default): every read returns at once, the
        newest value again if nothing new came (or ``initial`` before the first one; with
        neither, :class:`NoValueYet`). ``blocking=True``: a read waits for a new value.
        ``buffer_size``: values kept for ``read_many`` and blocking reads.
        Raises the server's reason (:class:`UnknownTypeError`, :class:`NoSuchFieldError`,
        :class:`TypeClashError`) if the binding is refused, and ``ValueError`` naming the
        option for a combination that cannot take effect (``initial`` with ``blocking``, ...).
        """
        flow = check_subscribe(transport, qos, policy, blocking=blocking,
                               buffer_size=buffer_size, has_initial=initial is not _MISSING)
        guard = fail_safe(policy.on_lost, self._events)
        ch_id = next(self._ids)
        kind = IncomingChannel if guard is None else GuardedChannel
        channel = kind(ch_id, topic, msg_type, field, transport=transport, blocking=blocking,
                       buffer_size=buffer_size, initial=initial, latest=policy.latest,
                       max_age_ms=policy.max_age_ms, link=self._conn.link,
                       credit_bell=self._sender.doorbell if flow else None)
        if isinstance(channel, GuardedChannel):
            channel.failsafe = guard
        channel.read_idle = self._conn.idle  # blocking reads wait as the receive thread does
        with self._lock:
            self._incoming[ch_id] = channel
        try:
            ack = self._conn.request_topic(TopicConnect(
                ch_id, "subscribe", topic, msg_type, field, transport, buffer_size,
                max_age_ms=policy.max_age_ms, redundancy=policy.redundancy,
                latest=policy.latest, reliability=qos.reliability, depth=qos.depth, flow=flow,
                durability=qos.durability))
        except BaseException:
            with self._lock:
                self._incoming.pop(ch_id, None)
            raise
        channel.msg_type = ack.msg_type
        if flow:
            self._sender.add_credit(channel)
        channel.on_close = self._unbind
        return channel

    def publish(
        self,
        topic: str,
        msg_type: str,
        field: str | None = "data",
        *,
        transport: Transport = "udp",
        qos: QoS = _DEFAULT_QOS,
        policy: Policy = _DEFAULT_POLICY,
        through_buffer: bool = False,
        buffer_size: int = 1024,
    ) -> OutgoingChannel:
        """A channel whose values are published on ``topic`` (``field=None``: whole messages).

        ``transport``, ``qos`` and ``policy`` as in :meth:`subscribe`; for a publisher the
        policy may also limit the rate (``Policy(max_rate_hz=..., adapt_rate=...)``, the rest
        waiting in the buffer) and ``max_age_ms`` is enforced here before sending and by the
        server before publishing. ``QoS(durability="transient_local")`` makes a latched topic.

        ``through_buffer=False``: each ``write`` hands the value to the send thread at once.
        ``through_buffer=True``: values wait in the channel until :meth:`send` or the send loop
        (``connect(send_rate_hz=...)``). Either way ``write`` never blocks and never touches a
        socket; a full buffer (``buffer_size`` values) drops its oldest value and counts it
        (``statistics().overwritten``). A flow-controlled channel (TCP, not latest) sends only
        what the subscribers have room for; ``wait_writable()`` paces a writer that must lose
        nothing. docs/policies.md says what each policy promises.
        """
        flow = check_publish(transport, qos, policy, buffer_size=buffer_size)
        ch_id = next(self._ids)
        channel = OutgoingChannel(ch_id, topic, msg_type, field, transport=transport,
                                  immediate=not through_buffer, buffer_size=buffer_size,
                                  doorbell=self._sender.doorbell, redundancy=policy.redundancy,
                                  latest=policy.latest, max_age_ms=policy.max_age_ms,
                                  link=self._conn.link, max_rate_hz=policy.max_rate_hz,
                                  adapt_rate=policy.adapt_rate, flow=flow)
        ack = self._conn.request_topic(TopicConnect(
            ch_id, "publish", topic, msg_type, field, transport, buffer_size,
            max_age_ms=policy.max_age_ms, redundancy=policy.redundancy, latest=policy.latest,
            reliability=qos.reliability, depth=qos.depth, flow=flow, loss_report=True,
            durability=qos.durability))
        channel.bound(ack)
        with self._lock:
            self._outgoing[ch_id] = channel
        self._sender.add(channel)
        channel.on_close = self._unbind
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
        """Unbind one channel on the server and close it here: ``channel.close()`` (or the
        end of a ``with`` block) does the same."""
        channel.close()
        self._unbind(channel)

    def _unbind(self, channel: IncomingChannel | OutgoingChannel) -> None:
        """A channel of this bridge was closed: stop serving it and unbind it on the server.
        Channels the bridge itself closes (its own close, a refused rebinding) are no longer
        registered when they close, so nothing is sent for them. A publish channel's last
        values go first, while it is registered: the loss reports confirming them reach it
        (:func:`~rlbridge.client.session.goodbye.deliver_last`)."""
        with self._lock:
            last = self._outgoing.get(channel.channel_id)
        if last is channel and self._conn.up:
            with contextlib.suppress(OSError, ConnectionClosed):
                deliver_last(last, self._conn, self._feedback.reported,
                             lambda bound: self._sender.flush(wait=True, timeout=bound))
        with self._lock:
            incoming = self._incoming.pop(channel.channel_id, None)
            out = self._outgoing.pop(channel.channel_id, None)
        if incoming is None and out is None:
            return
        if out is not None:
            self._sender.remove(out)
        if incoming is not None:
            self._sender.remove_credit(incoming)
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

    # -- status -----------------------------------------------------------------------------
    @property
    def link_state(self) -> LinkState:
        """``connected``, ``degraded`` or ``lost``: read it from control code, it never blocks.

        ``lost`` from the end of a session until its channels are bound again. The same
        source as the fail-safes and the link events: once this says ``lost``, they have
        engaged and the event is in every ``link_events()`` channel.
        """
        return self._events.last.state

    @property
    def state(self) -> ClientState:
        """``connected``, ``reconnecting`` or ``closed`` (for good)."""
        return self._conn.state

    @property
    def closed(self) -> bool:
        """True once the bridge is closed for good: here, or its session ended without reconnect."""
        return self._conn.closed.is_set()

    @property
    def close_reason(self) -> str:
        """Why the last session ended (``""`` while the first one is open)."""
        return self._conn.close_reason

    @property
    def reconnects(self) -> int:
        """Sessions opened again after one ended (0 with ``reconnect=False``)."""
        return 0 if self._supervisor is None else self._supervisor.reconnects

    def on_link_change(self, callback: Callable[[LinkState], None]) -> None:
        """Call ``callback(state)`` in the SDK thread that saw the change; keep it short."""
        self._events.add_callback(callback)

    def link_events(self, buffer_size: int = DEFAULT_EVENT_BUFFER) -> Channel[LinkEvent]:
        """A FIFO of :class:`LinkEvent` values: every link change (and first-hop loss report),
        each read once, in order.

        Its first event is the current state. ``try_read()`` raises :class:`WouldBlock` when
        nothing new is there, ``read(timeout)`` waits for the next event, ``read_many()``
        takes every event not read yet (``[]`` when none). Events are not state: the state now
        is :attr:`link_state`. A reader that falls ``buffer_size`` events behind loses the
        oldest (``statistics().overwritten``). Closed with the bridge (events still buffered
        stay readable, then ``ChannelClosed``).
        """
        return self._events.channel(buffer_size)

    @property
    def rtt_ns(self) -> int:
        """Smoothed round-trip time from heartbeats (-1 until measured)."""
        link = self._conn.link
        return -1 if link is None else link.stats(0).rtt_ns

    @property
    def local_ports(self) -> dict[str, int]:
        """The current session's local TCP and UDP ports (they change with every reconnect)."""
        return self._conn.local_ports()

    def server_stats(self) -> dict[str, Any]:
        """The server's counters for this session, its totals, and the topics it knows.

        A UDP-only session (``Tuning(control="udp")``) gets them in one datagram: when they do
        not fit one, the server's refusal is raised at once (:class:`RemoteError`,
        ``TOO_LARGE``, its reason says to ask over TCP)."""
        return dict(self._conn.request_stats())

    @property
    def session_id(self) -> int:
        """The number the server gave this session: it names it in logs and ``rlbridge stats``."""
        assert self._conn.ack is not None
        return self._conn.ack.session

    # -- services ------------------------------------------------------------------------
    def call(self, service: str, srv_type: str, request: dict[str, Any] | None = None, *,
             timeout: float = DEFAULT_TIMEOUT) -> dict[str, Any]:
        """Call a middleware service and wait for its response (a dict of its fields).

        ``srv_type`` as ``'std_srvs/srv/SetBool'``. Blocks up to ``timeout`` seconds (plus
        the network): for soft-real-time threads; a loop uses :meth:`service_client`.
        Raises ``UnknownTypeError``, ``BadValueError`` (the request does not fit the type),
        ``NoServiceError`` (no server within the timeout), ``ServiceTimeout`` (no answer),
        ``ServiceFailed`` (the server failed), all :class:`~rlbridge.wire.RemoteError`.
        """
        return self._conn.services.call(service, srv_type, request or {}, timeout)

    def service_client(self, service: str, srv_type: str, *, buffer_size: int = 16,
                       timeout: float = DEFAULT_TIMEOUT) -> ServiceClient:
        """Calls for a loop that must not block: ``client.request(req)`` (or
        ``client.requests.write``), later ``client.responses.try_read()`` ->
        :class:`~rlbridge.client.service_client.CallResult`.
        ``client.close()`` stops it."""
        return ServiceClient(self._conn.services, service, srv_type, buffer_size=buffer_size,
                             timeout=timeout)

    def serve_service(self, service: str, srv_type: str) -> ServiceRequests:
        """Provide ``service``: a channel of requests; ``req = requests.read(timeout=...)``,
        then ``req.data`` (a dict) and ``req.reply(response_dict)`` (or ``req.fail(reason)``).

        ``requests.close()`` withdraws the service. Raises ``UnknownTypeError`` for an
        unknown type and ``BindingRefused`` when the service is provided already.
        """
        ch_id = next(self._ids)
        requests = ServiceRequests(ch_id, service, srv_type)
        conn = self._conn
        conn.services.add_served(requests)
        try:
            conn.request_topic(ServiceOffer(ch_id, service, srv_type))
        except BaseException:
            conn.services.forget_served(ch_id)
            raise

        def withdraw() -> None:
            conn.services.forget_served(ch_id)
            conn.forget_topic(ch_id)
            if conn.up:
                with contextlib.suppress(OSError, ConnectionClosed):
                    conn.send_control(TopicClose(ch_id))

        requests._on_close = withdraw
        return requests

    def service_list(self) -> list[tuple[str, str]]:
        """The services the server's middleware knows, as ``(name, type)``."""
        body = self._conn.request_stats({"services": True})
        found: Any = body.get("services", [])
        return [(str(n), str(t)) for n, t in found]

    # -- actions -----------------------------------------------------------------------
    def send_goal(self, action: str, action_type: str, goal: dict[str, Any] | None = None, *,
                  feedback_buffer: int = 1024, timeout: float = DEFAULT_TIMEOUT) -> Goal:
        """Send an action goal; returns once the action server accepted it.

        ``goal.feedback`` is a channel of feedback dicts, ``goal.result(timeout=...)`` waits
        for the result dict (``goal.status``: ``succeeded``, ``canceled``, ``aborted``),
        ``goal.cancel()`` asks for a cancel. Raises ``NoServiceError`` (no action server),
        ``GoalRejected``, ``UnknownTypeError``, ``BadValueError``, ``ServiceTimeout``.
        """
        conn = self._conn
        ch_id = next(self._ids)
        feedback = IncomingChannel(ch_id, action, action_type, None, transport="tcp",
                                   blocking=True, buffer_size=feedback_buffer,
                                   link=conn.link)
        handle = Goal(conn, ch_id, action, feedback)

        def forget() -> None:
            with self._lock:
                self._incoming.pop(ch_id, None)

        handle.on_finish = forget
        with self._lock:
            self._incoming[ch_id] = feedback
        with conn.services.lock:
            conn.services.goals[ch_id] = handle
        try:
            conn.request_topic(GoalSend(ch_id, action, action_type, goal or {},
                                        max(1, round(timeout * 1000))))
        except BaseException:
            with conn.services.lock:
                conn.services.goals.pop(ch_id, None)
            with self._lock:
                self._incoming.pop(ch_id, None)
            raise
        finally:
            conn.forget_topic(ch_id)  # a goal is not sent again after a reconnect
        return handle

    # -- the server's own answers ---------------------------------------------------------
    def _on_ros_loss(self, channel: int, ros_lost: int) -> None:
        """Receive thread: the server counted ROS-side loss of a channel (``health()``)."""
        found: IncomingChannel | OutgoingChannel | None = self._incoming.get(channel)
        if found is None:  # not ``or``: an empty channel is falsy
            found = self._outgoing.get(channel)
        if found is not None:
            found.ros_lost = ros_lost

    # -- parameters --------------------------------------------------------------------
    def get_parameter(self, node: str, name: str, *,
                      timeout: float = DEFAULT_TIMEOUT) -> parameters.ParameterValue:
        """The value of parameter ``name`` of ROS node ``node`` (``ParameterError`` if unset)."""
        answer = self.call(parameters.node_service(node, "get_parameters"), parameters.GET,
                           {"names": [name]}, timeout=timeout)
        values = answer.get("values") or [{}]
        value = parameters.from_ros(values[0])
        if value is None:
            raise ParameterError(f"node {node} has no parameter '{name}'")
        return value

    def set_parameter(self, node: str, name: str, value: Any, *,
                      timeout: float = DEFAULT_TIMEOUT) -> None:
        """Set parameter ``name`` of ``node``; ``ParameterError`` with the node's reason if it
        refuses (undeclared, read-only, wrong type)."""
        answer = self.call(parameters.node_service(node, "set_parameters"), parameters.SET,
                           {"parameters": [{"name": name, "value": parameters.to_ros(value)}]},
                           timeout=timeout)
        result = (answer.get("results") or [{}])[0]
        if not result.get("successful"):
            raise ParameterError(
                f"node {node} refused {name}={value!r}: {result.get('reason') or 'no reason'}")

    def list_parameters(self, node: str, *, timeout: float = DEFAULT_TIMEOUT) -> list[str]:
        """The names of every parameter of ``node``, sorted."""
        answer = self.call(parameters.node_service(node, "list_parameters"), parameters.LIST,
                           {"prefixes": [], "depth": 0}, timeout=timeout)
        return sorted(answer.get("result", {}).get("names", []))

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
        for bound in self._conn.bindings():
            req = bound
            incoming = self._incoming.get(req.channel)
            outgoing = self._outgoing.get(req.channel)
            if incoming is not None:
                room = incoming.restart_sequence()  # before the request: values may follow
                incoming.relink(self._conn.link)
                if incoming.flow and isinstance(req, TopicConnect):  # the first credit
                    req = msgspec.structs.replace(req, buffer_size=room)
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

        The goodbye comes after the last values, which the server takes first: bounded by
        the link's timeout, what it has not confirmed by then is counted in the channel's
        ``health().lost`` and logged (:mod:`rlbridge.client.session.goodbye`). Prompt in
        every other phase: a reconnect backoff ends at once and a handshake is aborted.
        """
        if self._supervisor is not None:
            self._supervisor.request_stop()
        self._sender.close()
        with self._lock:
            outgoing = list(self._outgoing.values())
        self._conn.close(Goodbye(outgoing, self._feedback.reported))
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

