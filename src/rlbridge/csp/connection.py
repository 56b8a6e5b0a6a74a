"""The client's sockets and its receive thread: handshake, control requests, incoming values.

Theory of operation. ``Connection.open`` does the handshake in the caller's thread (it is the
only blocking network call control code ever makes, and it happens before any loop runs). Then
one receive thread owns reading: it waits in ``select`` on the TCP and UDP sockets (blocked in
C, holding no GIL), decodes whole packets with the sans-IO codec, and hands values to channels.
The same thread sends heartbeats and runs the watchdog, with timeouts taken from the
:class:`~rlbridge.wire.link.LinkMonitor`. Outgoing values are the send thread's business
(:mod:`rlbridge.csp.sender`); writes to the TCP socket from both threads go through one lock so
frames never interleave.

Sessions. One handshake and one receive thread make a *session*; a session ends when the server
hangs up, a socket breaks, or (with ``keep_alive``) the watchdog hears nothing for the server's
``timeout_ms``. Without ``keep_alive`` that is the end of the connection (``closed``, as
before); with it the connection waits in ``RECONNECTING`` until :meth:`reopen` (called by
:class:`~rlbridge.csp.reconnect.ReconnectSupervisor`) runs the same :meth:`_handshake` again.
Only :meth:`close` (or a session ending without ``keep_alive``) closes it for good.
"""

from __future__ import annotations

import collections
import contextlib
import errno
import logging
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import msgspec

from rlbridge.csp.reconnect import ClientState
from rlbridge.wire import (
    PROTOCOL_VERSION,
    AuthChallenge,
    Batch,
    ConnectAck,
    ConnectError,
    Disconnect,
    Error,
    FrameDecoder,
    Heartbeat,
    Hello,
    LocalProtocolError,
    Malformed,
    Packet,
    PacketCodec,
    RemoteProtocolError,
    RlbridgeError,
    Stats,
    TopicAck,
    TopicConnect,
    TopicError,
    Value,
    error_from_code,
)
from rlbridge.wire.link import LinkMonitor, LinkState

if TYPE_CHECKING:
    from rlbridge.csp.auth import ClientAuth

log = logging.getLogger("rlbridge.client")

Control = Literal["tcp", "udp"]

#: Datagrams read before the values gathered so far are handed to the channels.
RUN_DATAGRAMS = 32
#: Datagrams read in one go before the receive thread serves its other duties.
MAX_DRAIN = 256
#: Bytes of queued datagrams the client's UDP socket asks the kernel for.
UDP_RECEIVE_BUFFER = 4 << 20


class ConnectionFailed(RlbridgeError):
    """The bridge server could not be reached or refused the session."""


class ConnectionClosed(RlbridgeError):
    """The connection was closed (by this program, the server, or the watchdog)."""


#: ``(channel, first_seq, stamps, values)``: how the receive thread hands values to channels.
ValuesHandler = Callable[[int, int, list[int], list[object]], None]
#: ``(state, reason)``: called from the receive thread when the link state changes.
LinkHandler = Callable[[LinkState, str], None]


@dataclass
class _Pending:
    """A control request waiting for its answer from the receive thread."""

    done: threading.Event
    answer: Packet | None = None


class Connection:
    """Sockets, handshake, receive thread and watchdog of one session. See module docstring."""

    def __init__(self, host: str, port: int, *, name: str, nodelay: bool, control: Control,
                 timeout: float) -> None:
        self.host, self.port, self.name = host, port, name
        self.nodelay = nodelay
        self.control: Control = control
        self.timeout = timeout
        self.codec = PacketCodec()
        #: Pre-shared key (csp/auth.py); with one, the session is authenticated and sealed.
        self.psk: bytes | None = None
        self.auth: ClientAuth | None = None
        #: Datagrams the receive thread refused, by reason (bad_mac, replayed, bad_token, ...).
        self.datagrams_dropped: collections.Counter[str] = collections.Counter()
        self.tcp: socket.socket | None = None
        self.udp: socket.socket | None = None
        self.tcp_lock = threading.Lock()
        self.ack: ConnectAck | None = None
        self.link: LinkMonitor | None = None
        self.on_values: ValuesHandler | None = None
        self.on_link_change: LinkHandler | None = None
        self.on_error: Callable[[Error], None] | None = None
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
        self._handshaking = False
        self._generation = 0
        self._pending: dict[int, _Pending] = {}
        #: Every binding the server acknowledged, by channel: what a new session binds again.
        self._bindings: dict[int, TopicConnect] = {}
        self._pending_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._wake_r, self._wake_w = socket.socketpair()
        self._link_state = LinkState.CONNECTED
        self._stats_waiters: list[_Pending] = []
        self._leftover: list[Packet | Malformed] = []
        #: Values of the read burst in progress, per channel: ``(first_seq, stamps, values)``.
        self._runs: dict[int, tuple[int, list[int], list[object]]] = {}

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
        self._end_session("starting a new session", self._generation)
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
        from rlbridge.csp.auth import ClientAuth

        self.auth = ClientAuth(self.psk, self.name) if self.psk else None
        self.codec = PacketCodec()  # unsealed until this handshake's keys exist (reopening)
        hello = Hello(PROTOCOL_VERSION, self.name, self.auth.nonce if self.auth else b"")
        try:
            ack = self._open_tcp(hello) if self.control == "tcp" else self._open_udp(hello)
            if self.auth is not None:
                self.codec = self.auth.sealed(ack)
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
            self._runs = {}
            self._link_state = LinkState.CONNECTED
            self._session_ended = False
            self.state = ClientState.CONNECTED
            self._thread = threading.Thread(target=self._receive_loop, args=(self._generation,),
                                            name="rlbridge-recv", daemon=True)
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
    def receive_thread_id(self) -> int | None:
        """Native id of the current session's receive thread (``None`` when none runs)."""
        thread = self._thread
        return thread.native_id if thread is not None and thread.is_alive() else None

    def _open_tcp(self, hello: Hello) -> ConnectAck:
        self.tcp = sock = self._connect_tcp()
        if self.nodelay:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.sendall(self.codec.encode_frame(hello))
        decoder = FrameDecoder(self.codec)
        deadline = time.monotonic() + self.timeout
        while True:
            sock.settimeout(max(0.01, deadline - time.monotonic()))
            try:
                data = sock.recv(65536)
            except TimeoutError:
                raise ConnectionFailed(
                    f"no answer from {self.host}:{self.port} within {self.timeout} s") from None
            if not data:
                raise ConnectionFailed(f"{self.host}:{self.port} closed the connection")
            packets = decoder.feed(data)
            if self.auth is not None and packets and isinstance(packets[0], AuthChallenge):
                sock.sendall(self.codec.encode_frame(self.auth.answer(packets[0], sock)))
                packets = packets[1:]
            if packets:
                first = packets[0]
                break
        sock.settimeout(None)
        if isinstance(first, Malformed):
            raise ConnectionFailed(f"server sent an invalid packet: {first.error.reason}")
        ack = self._expect_ack(first)
        self._leftover = packets[1:]
        self.udp = self._udp_socket()
        return ack

    def _open_udp(self, hello: Hello) -> ConnectAck:
        self.udp = sock = self._udp_socket()
        datagram = self.codec.encode_datagram(hello, 0)
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline and not self.closed.is_set():
            sock.send(datagram)
            ready, _, _ = select.select([sock], [], [], 0.2)
            if ready:
                try:
                    data = sock.recv(65536)
                    packet = (self.auth.decode(self.codec, data) if self.auth is not None
                              else self.codec.decode_datagram(data)[2])
                except RemoteProtocolError:
                    continue  # not an answer to us (or forged): keep asking until the deadline
                if isinstance(packet, AuthChallenge) and self.auth is not None:
                    datagram = self.codec.encode_datagram(self.auth.answer(packet, sock), 0)
                    continue
                if isinstance(packet, Heartbeat):  # a live session whose ack was lost: ask again
                    continue
                self._leftover = []
                return self._expect_ack(packet)
        raise ConnectionFailed(
            f"no answer over UDP from {self.host}:{self.port} within {self.timeout} s")

    def _connect_tcp(self) -> socket.socket:
        """``connect`` that :meth:`close` can interrupt (a dropped SYN would wait ``timeout``)."""
        family, kind, proto, _name, address = socket.getaddrinfo(
            self.host, self.port, type=socket.SOCK_STREAM)[0]
        sock = socket.socket(family, kind, proto)
        try:
            sock.setblocking(False)
            err = sock.connect_ex(address)
            if err not in (0, errno.EINPROGRESS):
                raise OSError(err, os.strerror(err))
            ready, writable, _ = select.select([self._wake_r], [sock], [], self.timeout)
            if ready:
                raise ConnectionClosed("connection closed while connecting")
            if not writable:
                raise ConnectionFailed(
                    f"no answer from {self.host}:{self.port} within {self.timeout} s")
            err = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
            if err:
                raise OSError(err, os.strerror(err))
            sock.setblocking(True)
        except BaseException:
            sock.close()
            raise
        return sock

    def _udp_socket(self) -> socket.socket:
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_DGRAM)
        # Room for a burst while the receive thread waits for the GIL (the default ~200 KiB
        # holds under 100 full datagrams); capped by net.core.rmem_max, the rest are gaps.
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER)
        sock.connect((self.host, self.port))
        return sock

    def _expect_ack(self, packet: Packet) -> ConnectAck:
        if isinstance(packet, ConnectAck):
            return packet
        if isinstance(packet, ConnectError):
            from rlbridge.csp.auth import refused

            raise refused(packet)
        raise ConnectionFailed(f"server answered the hello with {type(packet).__name__}")

    # -- sending (any SRT thread) ------------------------------------------------------------
    def send_tcp(self, data: bytes | bytearray) -> None:
        tcp = self.tcp
        if tcp is None:
            raise ConnectionClosed("this session has no TCP connection")
        with self.tcp_lock:
            tcp.sendall(data)

    def send_udp(self, data: bytes) -> None:
        udp = self.udp
        if udp is None:
            raise ConnectionClosed("this session has no UDP socket")
        # ICMP port unreachable from an earlier datagram: the watchdog will tell.
        with contextlib.suppress(ConnectionRefusedError):
            udp.send(data)

    def send_control(self, packet: Packet) -> None:
        assert self.ack is not None
        if self.control == "tcp":
            self.send_tcp(self.codec.encode_frame(packet))
        else:
            self.send_udp(self.codec.encode_datagram(packet, self.ack.token))

    def send_udp_packet(self, packet: Packet) -> None:
        assert self.ack is not None
        self.send_udp(self.codec.encode_datagram(packet, self.ack.token))

    def request_topic(self, req: TopicConnect) -> TopicAck:
        """Send a topic-connect and wait for its answer; retransmit while the control is UDP.

        While the connection is reconnecting, waits for the next session (within ``timeout``);
        a session that ends before the answer arrives makes it ask again in the next one.
        """
        try:  # Structs are not validated when built: check locally, before the network
            msgspec.convert(msgspec.to_builtins(req), TopicConnect)
        except msgspec.ValidationError as exc:
            raise LocalProtocolError(f"invalid topic-connect for {req.topic!r}: {exc}") from None
        pending = _Pending(threading.Event())
        with self._pending_lock:
            self._pending[req.channel] = pending
        try:
            deadline = time.monotonic() + self.timeout
            while pending.answer is None:
                if self.closed.is_set():
                    raise ConnectionClosed(f"connection closed: {self.close_reason}")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ConnectionFailed(
                        f"no answer to the topic-connect for {req.topic} within {self.timeout} s")
                if not self._wait_up(left):
                    continue
                pending.done.clear()
                with contextlib.suppress(OSError, ConnectionClosed):  # session ended: retry
                    self.send_control(req)
                pending.done.wait(min(left, 0.25 if self.control == "udp" else left))
        finally:
            with self._pending_lock:
                self._pending.pop(req.channel, None)
        answer = pending.answer
        if isinstance(answer, TopicAck):
            with self._pending_lock:
                self._bindings[req.channel] = req
            return answer
        if isinstance(answer, TopicError):
            raise error_from_code(answer.code, answer.reason, channel=answer.channel)
        raise ConnectionClosed(f"connection closed: {self.close_reason}")

    def local_ports(self) -> dict[str, int]:
        """This session's local ports (``{"tcp": ..., "udp": ...}``), for logs and firewalls."""
        ports: dict[str, int] = {}
        for name, sock in (("tcp", self.tcp), ("udp", self.udp)):
            with contextlib.suppress(OSError):  # closed meanwhile: the session has ended
                if sock is not None:
                    ports[name] = sock.getsockname()[1]
        return ports

    def bindings(self) -> list[TopicConnect]:
        """The acknowledged bindings, oldest first (to bind again after a reconnect)."""
        with self._pending_lock:
            return list(self._bindings.values())

    def forget_topic(self, channel: int) -> None:
        """The channel was unbound: a new session does not bind it again."""
        with self._pending_lock:
            self._bindings.pop(channel, None)

    def _wait_up(self, timeout: float) -> bool:
        """Wait (at most ``timeout``) until a session is up or the connection closed."""
        with self._state_changed:
            return self._state_changed.wait_for(lambda: self.up or self.closed.is_set(),
                                                timeout) and self.up

    def request_stats(self) -> dict[str, object]:
        """Ask the server for its counters and topic list (``rlbridge stats``, ``topic list``)."""
        if not self._wait_up(self.timeout):
            raise ConnectionFailed(f"no session with the server within {self.timeout} s: "
                                   f"{self.close_reason}")
        pending = _Pending(threading.Event())
        with self._pending_lock:
            self._stats_waiters.append(pending)
        self.send_control(Stats())
        if not pending.done.wait(self.timeout) or not isinstance(pending.answer, Stats):
            raise ConnectionFailed(f"no statistics from the server within {self.timeout} s")
        return pending.answer.body

    # -- receiving (the receive thread) ------------------------------------------------------
    def _receive_loop(self, generation: int) -> None:
        decoder = FrameDecoder(self.codec)
        link = self.link
        assert link is not None
        assert self.ack is not None
        token = self.ack.token
        for packet in self._leftover:
            if not isinstance(packet, Malformed):
                self._dispatch(packet)
        self._leftover = []
        self._flush_values()
        sockets = [s for s in (self.tcp, self.udp, self._wake_r) if s is not None]
        try:
            if self.udp is not None and self.control == "tcp":
                self.send_udp_packet(link.make_heartbeat(time.monotonic_ns(), time.time_ns()))
            while generation == self._generation and self.up:
                now = time.monotonic_ns()
                timeout = max(0.0, (link.next_deadline(now) - now) / 1e9)
                readable, _, _ = select.select(sockets, [], [], timeout)
                for sock in readable:
                    if sock is self.tcp:
                        data = sock.recv(1 << 18)
                        if not data:
                            self._end_session("server closed the TCP connection", generation)
                            return
                        for packet in decoder.feed(data):
                            if isinstance(packet, Malformed):
                                log.warning("malformed packet from server: %s",
                                            packet.error.reason)
                            else:
                                self._dispatch(packet)
                    elif sock is self.udp:
                        self._receive_datagrams(sock, token)
                    else:
                        return
                # Last before blocking again: a woken reader then finds the GIL free soon.
                self._flush_values()
                self._tick(link, generation)
        except RemoteProtocolError as exc:
            self._end_session(f"server sent an invalid stream: {exc.reason}", generation)
        except OSError as exc:
            self._end_session(f"connection failed: {exc}", generation)

    def _receive_datagrams(self, sock: socket.socket, token: int) -> None:
        """Read the datagrams already queued (at most ``MAX_DRAIN``), without blocking.

        Values are handed on every ``RUN_DATAGRAMS`` datagrams (and when the queue is empty),
        so a long burst neither waits for its end nor costs a channel wake-up per datagram.
        After ``MAX_DRAIN`` datagrams the loop goes back to ``select``: under a flood the queue
        never empties, and heartbeats (the server's watchdog) and TCP must still be served.
        """
        for count in range(1, MAX_DRAIN + 1):
            if count % RUN_DATAGRAMS == 0:
                self._flush_values()
            try:
                data = sock.recv(65536, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionRefusedError:
                return
            try:
                _flags, got, packet = self.codec.decode_datagram(data)
            except RemoteProtocolError as exc:
                log.debug("dropped datagram: %s", exc.reason)
                self.datagrams_dropped[getattr(exc, "kind", "malformed")] += 1
                continue
            if got == token:
                self._dispatch(packet)
            else:
                self.datagrams_dropped["bad_token"] += 1

    def _tick(self, link: LinkMonitor, generation: int) -> None:
        now = time.monotonic_ns()
        state = link.state(now)
        if state is LinkState.LOST and self.keep_alive:
            # The server's watchdog has the same timeout: it has dropped this session too.
            self._end_session(f"watchdog: nothing from the server within "
                              f"{link.timeout_ns // 1_000_000} ms", generation)
            return
        if state is not self._link_state:
            silent_ms = link.stats(now).silence_ns // 1_000_000
            self._set_link(state, "heard from the server" if state is LinkState.CONNECTED
                           else f"nothing from the server for {silent_ms} ms")
        if link.heartbeat_due(now):
            hb = link.make_heartbeat(now, time.time_ns())
            if self.tcp is not None:
                self.send_tcp(self.codec.encode_frame(hb))
            if self.udp is not None:
                self.send_udp_packet(hb)

    def _dispatch(self, packet: Packet) -> None:
        link = self.link
        assert link is not None
        now = time.monotonic_ns()
        match packet:
            case Value():
                link.on_receive(now)
                self._gather(packet.channel, packet.seq, [packet.stamp_ns], [packet.value])
            case Batch():
                link.on_receive(now)
                self._gather(packet.channel, packet.first_seq, list(packet.stamps),
                             list(packet.values))
            case Heartbeat():
                link.on_heartbeat(packet, now, time.time_ns())
            case TopicAck(channel=ch) | TopicError(channel=ch):
                link.on_receive(now)
                with self._pending_lock:
                    pending = self._pending.get(ch)
                if pending is not None:
                    pending.answer = packet
                    pending.done.set()
            case Error():
                link.on_receive(now)
                log.warning("server reported: %s (code %d, channel %s)", packet.reason,
                            packet.code, packet.channel)
                if self.on_error is not None:
                    self.on_error(packet)
            case Stats():
                with self._pending_lock:
                    waiters, self._stats_waiters = self._stats_waiters, []
                for pending in waiters:
                    pending.answer = packet
                    pending.done.set()
            case ConnectError():
                self._end_session(f"server ended the session: {packet.reason}",
                                  self._generation)
            case Disconnect():
                self._end_session(f"server closed the session: {packet.reason or 'no reason'}",
                                  self._generation)
            case _:
                link.on_receive(now)

    def _gather(self, channel: int, first_seq: int, stamps: list[int],
                values: list[object]) -> None:
        """Add one packet's values (lists the caller gives away) to its channel's run.

        Consecutive packets of a channel become one run, handed to ``on_values`` once per read
        burst: one ring operation and at most one reader wake-up for many small packets. A
        packet that does not continue the run (a gap, a duplicate) starts a new one, so the
        channel's sequence tracker still sees every gap.
        """
        run = self._runs.get(channel)
        if run is not None:
            if first_seq == run[0] + len(run[2]):
                run[1].extend(stamps)
                run[2].extend(values)
                return
            self._deliver(channel, run)
        self._runs[channel] = (first_seq, stamps, values)

    def _flush_values(self) -> None:
        """Hand every gathered run to the channels (end of a read burst)."""
        runs = self._runs
        if runs:
            self._runs = {}
            for channel, run in runs.items():
                self._deliver(channel, run)

    def _deliver(self, channel: int, run: tuple[int, list[int], list[object]]) -> None:
        if self.on_values is not None:
            self.on_values(channel, run[0], run[1], run[2])

    @property
    def link_state(self) -> LinkState:
        if not self.up:
            return LinkState.LOST
        return self._link_state

    def _set_link(self, state: LinkState, reason: str) -> None:
        self._link_state = state
        if self.on_link_change is not None:
            self.on_link_change(state, reason)

    # -- closing ---------------------------------------------------------------------------
    def _end_session(self, reason: str, generation: int, *, final: bool = False) -> None:
        """End session ``generation`` (a stale one is ignored): reconnect later or close.

        Runs in the receive thread (hang-up, error, watchdog, goodbye), in the supervisor
        (:meth:`reopen`) or in the closing thread (``final``).
        """
        with self._state_changed:
            if generation != self._generation or self.closed.is_set():
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
            self._set_link(LinkState.LOST, reason)
        if self.on_session_end is not None:
            self.on_session_end(reason, final)
        with self._pending_lock:
            for pending in self._pending.values():
                pending.done.set()

    def close(self) -> None:
        """Say goodbye, stop the receive thread, close the sockets; idempotent.

        Also aborts a reconnect handshake running in another thread: the sockets are then
        released by that thread when its handshake fails.
        """
        if self.up and self.ack is not None:
            with contextlib.suppress(OSError, ConnectionClosed):
                self.send_control(Disconnect(0, "client closed"))
        self._end_session("closed by the client", self._generation, final=True)
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

    def _close_session_sockets(self) -> None:
        tcp, udp, self.tcp, self.udp = self.tcp, self.udp, None, None
        for sock in (tcp, udp):
            if sock is not None:
                sock.close()

    def _release(self) -> None:
        self._close_session_sockets()
        self._wake_r.close()
        self._wake_w.close()
