"""The client's connection to the server: the owner of its sessions and their lifetime.

Theory of operation. ``Connection.open`` does the handshake
(:mod:`rlbridge.client.session.handshake`) in
the caller's thread (it is the only blocking network call control code ever makes, and it
happens before any loop runs). Then one receive thread (:mod:`rlbridge.client.session.receiver`)
owns
reading: it waits in ``select`` on the TCP and UDP sockets, hands values to channels and
answers to the requests waiting for them (:mod:`rlbridge.client.session.pending`), sends heartbeats
and
runs the watchdog. Outgoing values are the send thread's business
(:mod:`rlbridge.client.session.sender`);
writes to the TCP socket from both threads go through one lock so frames never interleave.

Sessions. One handshake and one receive thread make a *session*; a session ends when the server
hangs up, a socket breaks, or (with ``keep_alive``) the watchdog hears nothing for the server's
``timeout_ms``. Without ``keep_alive`` that is the end of the connection (``closed``, as
before); with it the connection waits in ``RECONNECTING`` until :meth:`reopen` (called by
:class:`~rlbridge.client.session.reconnect.ReconnectSupervisor`) runs the same :meth:`_handshake`
again.
Only :meth:`close` (or a session ending without ``keep_alive``) closes it for good.
"""
from __future__ import annotations

import collections
import contextlib
import logging
import socket
import threading
import time
from collections.abc import Callable

from rlbridge.client.session import handshake
from rlbridge.client.session.auth import ClientAuth
from rlbridge.client.session.link_report import LinkReport
from rlbridge.client.session.pending import Requests
from rlbridge.client.session.receiver import Receiver
from rlbridge.client.session.reconnect import ClientState
from rlbridge.client.session.services import ServiceCalls
from rlbridge.client.session.session_owner import Control, ValuesHandler
from rlbridge.client.session.stream_guard import StreamGuard
from rlbridge.csp.idle import PARK, IdleStrategy
from rlbridge.errors import ConnectionClosed, ConnectionFailed
from rlbridge.tls import ClientTls
from rlbridge.wire import (
    PROTOCOL_VERSION,
    ConnectAck,
    Disconnect,
    Error,
    GoalSend,
    Hello,
    LossReport,
    Malformed,
    Packet,
    PacketCodec,
    ServiceOffer,
    TopicAck,
    TopicConnect,
)
from rlbridge.wire.codec import FLAG_BUNDLES
from rlbridge.wire.link import LinkMonitor, LinkState
from rlbridge.wire.seal import sealed_codec, tls_datagram_keys

# ConnectionFailed and ConnectionClosed are defined in session_errors (the handshake raises
# them too); this is the place to import them from, with Control, Connection's parameter.
__all__ = ["Connection", "ConnectionClosed", "ConnectionFailed", "Control"]

log = logging.getLogger("rlbridge.client")

#: What a client says when it closes its session.
GOODBYE = Disconnect(0, "client closed")


class Connection:
    """Sockets, handshake, receive thread and watchdog of one session. See module docstring."""

    def __init__(self, host: str, port: int, *, name: str, nodelay: bool, control: Control,
                 timeout: float, bundles: bool = True) -> None:
        self.host, self.port, self.name = host, port, name
        self.nodelay = nodelay
        self.control: Control = control
        self.timeout = timeout
        self.codec = PacketCodec()
        #: Flags of every datagram: ``FLAG_BUNDLES`` unless ``Tuning(bundles=False)``
        #: (the server then sends this client one datagram per channel, too).
        self.udp_flags = FLAG_BUNDLES if bundles else 0
        #: Pre-shared key (client/session/auth.py); with one, the session is authenticated and
        # sealed.
        self.psk: bytes | None = None
        self.auth: ClientAuth | None = None
        #: TLS settings (rlbridge.tls), and what protects the current session's TCP stream.
        self.tls: ClientTls | None = None
        self.guard = StreamGuard()
        #: Datagrams the receive thread refused, by reason (bad_mac, replayed, bad_token, ...).
        self.datagrams_dropped: collections.Counter[str] = collections.Counter()
        self.tcp: socket.socket | None = None
        self.udp: socket.socket | None = None
        self.tcp_lock = threading.Lock()
        #: Bytes written to the TCP connection (all sessions): the receive thread skips a TCP
        #: heartbeat after data (see ``Receiver``).
        self.tcp_bytes_out = 0
        self.ack: ConnectAck | None = None
        self.link: LinkMonitor | None = None
        self.on_values: ValuesHandler | None = None
        self.on_error: Callable[[Error], None] | None = None
        #: ``(channel, limit)``: the server granted a publish channel credit (receive thread).
        self.on_credit: Callable[[int, int], None] | None = None
        #: The server's first-hop loss report for publish channels (receive thread).
        self.on_loss: Callable[[LossReport], None] | None = None
        #: How the receive thread waits for a readable socket (csp/idle.py).
        self.idle: IdleStrategy = PARK
        #: ``(channel, ros_lost)``: the server's count of a channel's ROS-side loss (``RosLoss``).
        self.on_ros_loss: Callable[[int, int], None] | None = None
        #: Called with the reason when a session ends (before any reconnect), and once more,
        #: with ``final=True``, when the connection is closed for good.
        self.on_session_end: Callable[[str, bool], None] | None = None
        #: Set: a lost session leaves the connection RECONNECTING instead of closing it.
        self.keep_alive = False
        self.state = ClientState.CONNECTING
        self.closed = threading.Event()
        self.close_reason = ""
        self._state_lock = threading.Lock()
        self._state_changed = threading.Condition(self._state_lock)
        self._session_ended = False
        #: Set by :meth:`close` before its goodbye: the server's hang-up that answers it is
        #: not a lost link, and the session ends with the closing thread's reason.
        self._closing = False
        self._handshaking = False
        self._generation = 0
        #: Control requests waiting for answers, and the bindings a new session makes again.
        self.requests = Requests(self)
        #: Service calls in flight and the channels of provided services.
        self.services: ServiceCalls = ServiceCalls(self)
        self._thread: threading.Thread | None = None
        self._wake_r, self._wake_w = socket.socketpair()
        #: The link as told to the owner (client/session/link_report.py); its ``on_change`` is the
        #: owner's handler.
        self.link_report = LinkReport()
        self._leftover: list[Packet | Malformed] = []

    # -- opening ---------------------------------------------------------------------------
    def open(self) -> ConnectAck:
        """First session: handshake, then the receive thread. Raises :class:`ConnectionFailed`."""
        try:
            ack = self._handshake()
        except BaseException:
            with self._state_lock:
                self.closed.set()
                self.state = ClientState.CLOSED
            self._release()
            raise
        self._start_session(ack)
        return ack

    def reopen(self) -> None:
        """A new session after the last one ended (the reconnect supervisor calls this).

        Ends the current session first if one is still up (its channels failed to bind again),
        joins its receive thread, then runs the same handshake as :meth:`open`. Raises
        :class:`ConnectionFailed` (try again later) or :class:`ConnectionClosed` (closed here).
        """
        self.end_session("starting a new session", self._generation)
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(5.0)
        self._close_session_sockets()
        self._start_session(self._handshake())

    def _handshake(self) -> ConnectAck:
        """The handshake of every session, first and reconnect: sockets, hello, answer.

        :meth:`close` from another thread aborts it (wake-up socket, socket shutdown); the
        sockets are then released here, never under this thread's feet.
        """
        with self._state_lock:
            if self.closed.is_set():
                raise ConnectionClosed(f"connection closed: {self.close_reason}")
            self._handshaking = True
        self.auth = ClientAuth(self.psk, self.name) if self.psk else None
        self.codec = PacketCodec()  # unsealed until this handshake's keys exist (reopening)
        self.guard.reset()
        hello = Hello(PROTOCOL_VERSION, self.name, self.auth.nonce if self.auth else b"")
        try:
            ack, self._leftover = (handshake.open_tcp(self, hello, self._wake_r)
                                   if self.control == "tcp" else handshake.open_udp(self, hello))
            if self.auth is not None:
                self.codec = self.auth.sealed(ack)
            elif self.guard.tls is not None and ack.datagram_key:
                self.codec = sealed_codec(tls_datagram_keys(ack.datagram_key, ack.token),
                                          server=False)
            return ack
        except OSError as exc:
            self._close_session_sockets()
            raise ConnectionFailed(
                f"cannot reach rlbridge server at {self.host}:{self.port}: {exc.strerror or exc}"
            ) from None
        except BaseException:
            self._close_session_sockets()
            raise
        finally:
            with self._state_lock:
                self._handshaking = False
                aborted = self.closed.is_set()
            if aborted:  # close() ran meanwhile and left the sockets to this thread
                self._release()

    def _start_session(self, ack: ConnectAck) -> None:
        with self._state_changed:
            if self.closed.is_set():
                raise ConnectionClosed(f"connection closed: {self.close_reason}")
            self._generation += 1
            self.ack = ack
            self.link = LinkMonitor(time.monotonic_ns(), ack.heartbeat_ms * 1_000_000,
                                    ack.timeout_ms * 1_000_000)
            self.link_report.session_started(self._generation, told=self._generation == 1)
            self._session_ended = False
            self.state = ClientState.CONNECTED
            receiver = Receiver(self, self._generation, self._leftover, self._wake_r)
            self._leftover = []
            self._thread = threading.Thread(target=receiver.run, name="rlbridge-recv",
                                            daemon=True)
            self._thread.start()
            self._state_changed.notify_all()

    @property
    def up(self) -> bool:
        """True while a session is established (values and requests can go out)."""
        return self.state is ClientState.CONNECTED

    def wait_session_end(self, stop: threading.Event) -> bool:
        """Block until the current session has ended (True) or ``stop``/close (False).

        ``stop`` is honoured at once only if its setter also calls :meth:`wake` (the Bridge
        sets it together with closing this connection, which wakes every waiter).
        """
        with self._state_changed:
            self._state_changed.wait_for(
                lambda: self._session_ended or stop.is_set() or self.closed.is_set())
            return self._session_ended and not stop.is_set() and not self.closed.is_set()

    def wake(self) -> None:
        """Wake :meth:`wait_session_end` and requests waiting for a session, to re-check."""
        with self._state_changed:
            self._state_changed.notify_all()

    @property
    def generation(self) -> int:
        """The number of the current (or last) session, counting from 1."""
        return self._generation

    @property
    def receive_thread_id(self) -> int | None:
        """Native id of the current session's receive thread (``None`` when none runs)."""
        thread = self._thread
        return thread.native_id if thread is not None and thread.is_alive() else None

    # -- sending (any SRT thread) ------------------------------------------------------------
    def send_tcp(self, data: bytes | bytearray) -> None:
        """Write frames to the TCP connection (through TLS when on), whole, in call order."""
        tcp = self.tcp
        if tcp is None:
            raise ConnectionClosed("this session has no TCP connection")
        with self.tcp_lock:
            data = self.guard.protect(data)  # in the lock: records leave in counter order
            if data:
                tcp.sendall(data)
                self.tcp_bytes_out += len(data)

    def tcp_received(self, data: bytes) -> bytes:
        """The plaintext of bytes the TCP socket read (all of it: none left inside TLS)."""
        plain, reply = self.guard.open(data)
        if reply:  # e.g. a key update's answer: out in order with everything else
            self.send_tcp(b"")
        return plain

    def send_udp(self, data: bytes, flags: int = 0) -> None:
        udp = self.udp
        if udp is None:
            raise ConnectionClosed("this session has no UDP socket")
        try:  # noqa: SIM105 (suppress() costs two Python calls, and this runs every round)
            udp.send(data, flags)  # flags: MSG_DONTWAIT for send(inline=True)
        except ConnectionRefusedError:  # ICMP unreachable from an earlier one: the watchdog
            pass

    def send_control(self, packet: Packet) -> None:
        assert self.ack is not None
        if self.control == "tcp":
            self.send_tcp(self.codec.encode_frame(packet))
        else:
            self.send_udp(self.codec.encode_datagram(packet, self.ack.token, self.udp_flags))

    def send_udp_packet(self, packet: Packet) -> None:
        assert self.ack is not None
        self.send_udp(self.codec.encode_datagram(packet, self.ack.token, self.udp_flags))

    def request_topic(self, req: TopicConnect | ServiceOffer | GoalSend) -> TopicAck:
        """Send a topic-connect and wait for its answer; retransmit while the control is UDP.

        While the connection is reconnecting, waits for the next session (within ``timeout``);
        a session that ends before the answer arrives makes it ask again in the next one.
        """
        return self.requests.topic(req)

    def local_ports(self) -> dict[str, int]:
        """This session's local ports (``{"tcp": ..., "udp": ...}``), for logs and firewalls."""
        ports: dict[str, int] = {}
        for name, sock in (("tcp", self.tcp), ("udp", self.udp)):
            with contextlib.suppress(OSError):  # closed meanwhile: the session has ended
                if sock is not None:
                    ports[name] = sock.getsockname()[1]
        return ports

    def bindings(self) -> list[TopicConnect | ServiceOffer | GoalSend]:
        """The acknowledged bindings, oldest first (to bind again after a reconnect)."""
        return self.requests.bindings()

    def forget_topic(self, channel: int) -> None:
        """The channel was unbound: a new session does not bind it again."""
        self.requests.forget(channel)

    def wait_up(self, timeout: float) -> bool:
        """Wait (at most ``timeout``) until a session is up or the connection closed."""
        with self._state_changed:
            return self._state_changed.wait_for(lambda: self.up or self.closed.is_set(),
                                                timeout) and self.up

    def request_stats(self, ask: dict[str, object] | None = None) -> dict[str, object]:
        """Ask the server for its counters and topic list (``rlbridge stats``, ``topic list``);
        ``ask={"services": True}`` adds the service list."""
        return self.requests.stats(ask)

    @property
    def link_state(self) -> LinkState:
        if not self.up:
            return LinkState.LOST
        return self.link_report.state

    # -- closing ---------------------------------------------------------------------------
    def end_session(self, reason: str, generation: int, *, final: bool = False) -> None:
        """End session ``generation`` (a stale one is ignored): reconnect later or close.

        Runs in the receive thread (hang-up, error, watchdog, goodbye), in the supervisor
        (:meth:`reopen`) or in the closing thread (``final``).
        """
        with self._state_changed:
            if generation != self._generation or self.closed.is_set():
                return
            if self._closing and not final:
                return
            was_up = self.state is ClientState.CONNECTED
            final = final or not self.keep_alive
            if not (was_up or final):
                return
            self.close_reason = reason
            if final:
                self.closed.set()
                self.state = ClientState.CLOSED
            else:
                self.state = ClientState.RECONNECTING
                self._session_ended = True
            self._state_changed.notify_all()
        log.info("session ended (%s): %s", "closed" if final else "will reconnect", reason)
        if was_up:
            self.link_report.session_ended(reason)
        if self.on_session_end is not None:
            self.on_session_end(reason, final)
        self.requests.session_ended()
        self.services.session_ended(final)

    def close(self, goodbye: Callable[[Connection], None] | None = None) -> None:
        """Say goodbye, stop the receive thread, close the sockets; idempotent.

        ``goodbye`` says it when a session is up (``Bridge.close``: after its last values,
        :mod:`rlbridge.client.session.goodbye`); by default a ``Disconnect`` on the control
        transport. Also aborts a reconnect handshake running in another thread: the sockets
        are then released by that thread when its handshake fails.
        """
        with self._state_changed:
            self._closing = True  # first: the server's hang-up after a goodbye is no lost link
        if self.up and self.ack is not None:
            with contextlib.suppress(OSError, ConnectionClosed):
                if goodbye is None:
                    self.send_control(GOODBYE)
                else:
                    goodbye(self)
        self.end_session("closed by the client", self._generation, final=True)
        with self._state_lock:
            handshaking = self._handshaking
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        for sock in (self.tcp, self.udp):
            if sock is not None:  # wakes a recv blocked in a handshake or the receive thread
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)
        if not handshaking:
            self._release()

    def wait_hung_up(self, timeout: float) -> bool:
        """While closing: wait (at most ``timeout``) for the receive thread to end, which it
        does when the server closes the session's TCP connection; True if it has. False at
        once when called from that thread (it cannot wait for itself)."""
        thread = self._thread
        if thread is None or thread is threading.current_thread():
            return False
        thread.join(timeout)
        return not thread.is_alive()

    @property
    def receiving(self) -> bool:
        """The receive thread runs, and it is not the caller (:meth:`wait_hung_up` can wait)."""
        thread = self._thread
        return (thread is not None and thread is not threading.current_thread()
                and thread.is_alive())

    def _close_session_sockets(self) -> None:
        tcp, udp, self.tcp, self.udp = self.tcp, self.udp, None, None
        for sock in (tcp, udp):
            if sock is not None:
                sock.close()

    def _release(self) -> None:
        self._close_session_sockets()
        self._wake_r.close()
        self._wake_w.close()
