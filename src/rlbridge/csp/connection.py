"""The client's sockets and its receive thread: handshake, control requests, incoming values.

Theory of operation. ``Connection.open`` does the handshake in the caller's thread (it is the
only blocking network call control code ever makes, and it happens before any loop runs). Then
one receive thread owns reading: it waits in ``select`` on the TCP and UDP sockets (blocked in
C, holding no GIL), decodes whole packets with the sans-IO codec, and hands values to channels.
The same thread sends heartbeats and runs the watchdog, with timeouts taken from the
:class:`~rlbridge.wire.link.LinkMonitor`. Outgoing values are the send thread's business
(:mod:`rlbridge.csp.sender`); writes to the TCP socket from both threads go through one lock so
frames never interleave.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import select
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import msgspec

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
        self.on_link_change: Callable[[LinkState], None] | None = None
        self.on_error: Callable[[Error], None] | None = None
        self.closed = threading.Event()
        self.close_reason = ""
        self._pending: dict[int, _Pending] = {}
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
        """Handshake, then start the receive thread. Raises :class:`ConnectionFailed`."""
        from rlbridge.csp.auth import ClientAuth

        self.auth = ClientAuth(self.psk, self.name) if self.psk else None
        self.codec = PacketCodec()  # unsealed until this handshake's keys exist (reopening)
        hello = Hello(PROTOCOL_VERSION, self.name, self.auth.nonce if self.auth else b"")
        try:
            ack = self._open_tcp(hello) if self.control == "tcp" else self._open_udp(hello)
            if self.auth is not None:
                self.codec = self.auth.sealed(ack)
        except OSError as exc:
            self._close_sockets()
            raise ConnectionFailed(
                f"cannot reach rlbridge server at {self.host}:{self.port}: {exc.strerror or exc}"
            ) from None
        except BaseException:
            self._close_sockets()
            raise
        self.ack = ack
        self.link = LinkMonitor(time.monotonic_ns(), ack.heartbeat_ms * 1_000_000,
                                ack.timeout_ms * 1_000_000)
        self._thread = threading.Thread(target=self._receive_loop, name="rlbridge-recv",
                                        daemon=True)
        self._thread.start()
        return ack

    def _open_tcp(self, hello: Hello) -> ConnectAck:
        sock = socket.create_connection((self.host, self.port), timeout=self.timeout)
        self.tcp = sock
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
        while time.monotonic() < deadline:
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
        """Send a topic-connect and wait for its answer; retransmit while the control is UDP."""
        try:  # Structs are not validated when built: check locally, before the network
            msgspec.convert(msgspec.to_builtins(req), TopicConnect)
        except msgspec.ValidationError as exc:
            raise LocalProtocolError(f"invalid topic-connect for {req.topic!r}: {exc}") from None
        pending = _Pending(threading.Event())
        with self._pending_lock:
            self._pending[req.channel] = pending
        try:
            deadline = time.monotonic() + self.timeout
            while not pending.done.is_set():
                if self.closed.is_set():
                    raise ConnectionClosed(f"connection closed: {self.close_reason}")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ConnectionFailed(
                        f"no answer to the topic-connect for {req.topic} within {self.timeout} s")
                self.send_control(req)
                pending.done.wait(min(left, 0.25 if self.control == "udp" else left))
        finally:
            with self._pending_lock:
                self._pending.pop(req.channel, None)
        answer = pending.answer
        if isinstance(answer, TopicAck):
            return answer
        if isinstance(answer, TopicError):
            raise error_from_code(answer.code, answer.reason, channel=answer.channel)
        raise ConnectionClosed(f"connection closed: {self.close_reason}")

    def request_stats(self) -> dict[str, object]:
        """Ask the server for its counters and topic list (``rlbridge stats``, ``topic list``)."""
        pending = _Pending(threading.Event())
        with self._pending_lock:
            self._stats_waiters.append(pending)
        self.send_control(Stats())
        if not pending.done.wait(self.timeout) or not isinstance(pending.answer, Stats):
            raise ConnectionFailed(f"no statistics from the server within {self.timeout} s")
        return pending.answer.body

    # -- receiving (the receive thread) ------------------------------------------------------
    def _receive_loop(self) -> None:
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
        if self.udp is not None and self.control == "tcp":
            self.send_udp_packet(link.make_heartbeat(time.monotonic_ns()))
        sockets = [s for s in (self.tcp, self.udp, self._wake_r) if s is not None]
        try:
            while not self.closed.is_set():
                now = time.monotonic_ns()
                timeout = max(0.0, (link.next_deadline(now) - now) / 1e9)
                readable, _, _ = select.select(sockets, [], [], timeout)
                for sock in readable:
                    if sock is self.tcp:
                        data = sock.recv(1 << 18)
                        if not data:
                            self._shutdown("server closed the TCP connection")
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
                self._tick(link)
                # Last before blocking again: a woken reader then finds the GIL free soon.
                self._flush_values()
        except RemoteProtocolError as exc:
            self._shutdown(f"server sent an invalid stream: {exc.reason}")
        except OSError as exc:
            self._shutdown(f"connection failed: {exc}")

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

    def _tick(self, link: LinkMonitor) -> None:
        now = time.monotonic_ns()
        state = link.state(now)
        if state is not self._link_state:
            self._link_state = state
            if self.on_link_change is not None:
                self.on_link_change(state)
        if link.heartbeat_due(now):
            hb = link.make_heartbeat(now)
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
                link.on_heartbeat(packet, now)
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
                self._shutdown(f"server ended the session: {packet.reason}")
            case Disconnect():
                self._shutdown(f"server closed the session: {packet.reason or 'no reason'}")
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
        if self.closed.is_set():
            return LinkState.LOST
        return self._link_state

    # -- closing ---------------------------------------------------------------------------
    def _shutdown(self, reason: str) -> None:
        if self.closed.is_set():
            return
        self.close_reason = reason
        self.closed.set()
        log.info("connection closed: %s", reason)
        if self._link_state is not LinkState.LOST:
            self._link_state = LinkState.LOST
            if self.on_link_change is not None:
                self.on_link_change(LinkState.LOST)
        with self._pending_lock:
            for pending in self._pending.values():
                pending.done.set()

    def close(self) -> None:
        """Say goodbye, stop the receive thread, close the sockets; idempotent."""
        if not self.closed.is_set() and self.ack is not None:
            with contextlib.suppress(OSError):
                self.send_control(Disconnect(0, "client closed"))
        self._shutdown("closed by the client")
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)
        self._close_sockets()

    def _close_sockets(self) -> None:
        for sock in (self.tcp, self.udp, self._wake_r, self._wake_w):
            if sock is not None:
                sock.close()
