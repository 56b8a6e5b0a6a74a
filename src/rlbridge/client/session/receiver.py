"""The receive thread of one client session: poll loop, datagrams, dispatch, heartbeats.

One :class:`Receiver` per session (generation) of a
:class:`~rlbridge.client.session.connection.Connection`; its :meth:`Receiver.run` is the body of the
``rlbridge-recv`` thread. It waits in ``poll`` on the TCP and UDP sockets and the
connection's wake-up socket (blocked in C, holding no GIL), decodes whole packets with the
sans-IO codec, and gathers consecutive values of a channel into runs handed to the channels
once per read burst. Between reads it sends heartbeats and runs the watchdog, with timeouts
taken from the session's :class:`~rlbridge.wire.link.LinkMonitor`. It ends when the session
does: the connection's generation moves on, the session is no longer up, or the wake-up
socket is readable (``close``). How it waits is the connection's idle strategy
(:mod:`rlbridge.csp.idle`): ``poll`` with the timeout (park), or zero-timeout ``poll``
calls first (spin); a spinning strategy applies only while the session has something coming
in (:func:`listening`), else the thread parks, as a publish-only client's has only heartbeats
and answers to read (docs/concepts.md, idle strategies). ``Credit`` and ``LossReport``
packets go to the connection's handlers.
"""

from __future__ import annotations

import logging
import select
import socket
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from rlbridge.csp.idle import Park
from rlbridge.wire import (
    Batch,
    Bundle,
    ConnectError,
    Credit,
    Disconnect,
    Error,
    FrameDecoder,
    GoalResult,
    Heartbeat,
    LossReport,
    Malformed,
    Packet,
    RemoteProtocolError,
    RosLoss,
    ServiceRequest,
    ServiceResult,
    Stats,
    TopicAck,
    TopicError,
    Value,
)
from rlbridge.wire.link import LinkMonitor, LinkState

if TYPE_CHECKING:
    from rlbridge.client.session.session_owner import SessionOwner

log = logging.getLogger("rlbridge.client")

#: Datagrams read before the values gathered so far are handed to the channels.
RUN_DATAGRAMS = 32
#: Datagrams read in one go before the receive thread serves its other duties.
MAX_DRAIN = 256


def listening(conn: SessionOwner) -> bool:
    """The session has something coming in at a rate: a subscription, a provided service, or
    a service call or goal waiting for its answer. Without one (a publish-only client) the
    receive thread parks whatever its idle strategy: it would spin for heartbeats and answers.
    """
    return conn.requests.incoming > 0 or conn.services.waiting


class Receiver:
    """Reading for session ``generation`` of ``conn``; see the module docstring."""

    def __init__(self, conn: SessionOwner, generation: int,
                 leftover: list[Packet | Malformed], wake: socket.socket) -> None:
        self._conn = conn
        self._generation = generation
        self._leftover = leftover
        self._wake = wake
        self._tcp_bytes_at_heartbeat = (-1, -1)
        self._tcp_bytes_in = 0
        #: Values of the read burst in progress, per channel: ``(first_seq, stamps, values)``.
        self._runs: dict[int, tuple[int, list[int], list[object]]] = {}

    def run(self) -> None:
        """The thread's body: packets that came with the ack first, then the loop."""
        conn, generation = self._conn, self._generation
        decoder = conn.guard.decoder or FrameDecoder(conn.codec)
        link = conn.link
        assert link is not None
        assert conn.ack is not None
        token = conn.ack.token
        for packet in self._leftover:
            if not isinstance(packet, Malformed):
                self._dispatch(packet)
        self._leftover = []
        self._flush_values()
        wait, queued = self._pollers()
        tcp_fd = conn.tcp.fileno() if conn.tcp is not None else -1
        udp_fd = conn.udp.fileno() if conn.udp is not None else -1
        idle = conn.idle

        def poll() -> list[tuple[int, int]]:
            return wait(0)

        def block(timeout: float | None) -> list[tuple[int, int]]:
            return wait(None if timeout is None else timeout * 1000.0)

        try:
            if conn.udp is not None and conn.control == "tcp":
                conn.send_udp_packet(link.make_heartbeat(time.monotonic_ns(), time.time_ns()))
            now = time.monotonic_ns()
            timeout = max(0.0, (link.next_deadline(now) - now) / 1e9)
            park = isinstance(idle, Park)  # the default: straight into poll, no two calls
            while generation == conn.generation and conn.up:
                if park or not listening(conn):  # nothing comes in at a rate: park (module doc)
                    readable = wait(timeout * 1000.0)
                else:
                    readable = idle.idle(poll, block, timeout)
                tcp, udp = conn.tcp, conn.udp
                for fd, _events in readable:
                    if fd == tcp_fd and tcp is not None:
                        data = tcp.recv(1 << 18)
                        self._tcp_bytes_in += len(data)
                        if not data:
                            conn.end_session("server closed the TCP connection", generation)
                            return
                        # The packets before a header that broke the stream still count:
                        # handed on first, then the fault ends the session.
                        packets, fault = decoder.feed_until_fault(conn.tcp_received(data))
                        self._stream(packets)
                        if fault is not None:
                            self._flush_values()
                            raise fault
                    elif fd == udp_fd and udp is not None:
                        self._receive_datagrams(udp, token, queued)
                    else:
                        return
                timeout = self._tick(link, generation)
                # Last before blocking again: the reader this wakes needs the GIL, and finds
                # it free when this thread is back in poll by then (measured: handing values
                # on before more Python or a system call costs the reader a second wake-up,
                # on the GIL).
                self._flush_values()
        except RemoteProtocolError as exc:
            conn.end_session(f"server sent an invalid stream: {exc.reason}", generation)
        except OSError as exc:
            conn.end_session(f"connection failed: {exc}", generation)

    def _pollers(self) -> tuple[Callable[..., list[tuple[int, int]]],
                                Callable[..., list[tuple[int, int]]]]:
        """The session's two ``poll`` calls: every socket and the wake-up, then the UDP
        socket alone.

        One poll object per session, registered once: no descriptor sets built per wake-up
        (as select() does), and the answer is file descriptors, compared as ints. The UDP
        one asks "is another datagram queued?" after the first of a wake-up (a zero-timeout
        poll costs a third of a ``recv`` that fails with EAGAIN).
        """
        conn = self._conn
        poller, udp_poller = select.poll(), select.poll()
        for sock in (conn.tcp, conn.udp, self._wake):
            if sock is not None:
                poller.register(sock, select.POLLIN)
        if conn.udp is not None:
            udp_poller.register(conn.udp, select.POLLIN)
        return poller.poll, udp_poller.poll

    def _receive_datagrams(self, sock: socket.socket, token: int,
                           queued: Callable[[int], list[tuple[int, int]]]) -> None:
        """Read the datagrams already queued (at most ``MAX_DRAIN``), without blocking.

        ``poll`` said the socket is readable, so the first ``recv`` finds a datagram; whether
        another follows is asked of ``queued`` (a zero-timeout poll of this socket) rather
        than of a ``recv`` that fails with EAGAIN and raises: in the steady state of one
        datagram per wake-up that is the cheaper question. Once a second datagram was there
        the queue is read until EAGAIN (a burst).
        Values are handed on every ``RUN_DATAGRAMS`` datagrams (and by ``run`` when the
        queue is empty), so a long burst neither waits for its end nor costs a channel
        wake-up per datagram.
        After ``MAX_DRAIN`` datagrams the loop goes back to ``poll``: under a flood the queue
        never empties, and heartbeats (the server's watchdog) and TCP must still be served.
        """
        conn = self._conn
        decode = conn.codec.decode_datagram
        recv = sock.recv
        bundles = 0
        for count in range(1, MAX_DRAIN + 1):
            try:
                data = recv(65536, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionRefusedError:
                break
            try:
                _flags, got, packet = decode(data)
            except RemoteProtocolError as exc:
                log.debug("dropped datagram: %s", exc.reason)
                conn.datagrams_dropped[getattr(exc, "kind", "malformed")] += 1
            else:
                if got != token:
                    conn.datagrams_dropped["bad_token"] += 1
                elif type(packet) is Bundle:
                    bundles += 1
                    self._bundle(packet.parts)
                else:
                    self._dispatch(packet)
            if count % RUN_DATAGRAMS == 0:
                self._flush_values()
            elif count == 1 and not queued(0):
                break
        if bundles:
            link = conn.link
            assert link is not None
            link.on_receive(time.monotonic_ns())  # one arrival for the read's bundles

    def _bundle(self, parts: list[Value | Batch]) -> None:
        """A bundle's parts, each as if it had come alone: ``_gather`` inlined for a
        ``Value`` that starts or continues its channel's run (nearly every part), and a
        ``Batch``'s lists given away (the packet is dropped after this)."""
        # inlines: Receiver._gather
        runs = self._runs
        for part in parts:
            if isinstance(part, Value):
                channel, seq = part.channel, part.seq
                run = runs.get(channel)
                if run is None:
                    runs[channel] = (seq, [part.stamp_ns], [part.value])
                elif seq == run[0] + len(run[2]):
                    run[1].append(part.stamp_ns)
                    run[2].append(part.value)
                else:
                    self._gather(channel, seq, [part.stamp_ns], [part.value])
            else:
                self._gather(part.channel, part.first_seq, part.stamps, part.values)

    def _tick(self, link: LinkMonitor, generation: int) -> float:
        """Watchdog and heartbeats, after every wake-up of the loop; returns the seconds
        until the link's next deadline (how long the next ``poll`` may wait)."""
        conn = self._conn
        now = time.monotonic_ns()
        state = link.state(now)
        if state is LinkState.LOST and conn.keep_alive:
            # The server's watchdog has the same timeout: it has dropped this session too.
            conn.end_session(f"watchdog: nothing from the server within "
                             f"{link.timeout_ns // 1_000_000} ms", generation)
            return 0.0
        if state is not conn.link_report.state:
            silent_ms = link.stats(now).silence_ns // 1_000_000
            conn.link_report.update(state, "heard from the server" if state is LinkState.CONNECTED
                          else f"nothing from the server for {silent_ms} ms", generation)
        if link.heartbeat_due(now):
            hb = link.make_heartbeat(now, time.time_ns())
            # Not on a TCP connection that carried data either way since the last heartbeat
            # when UDP is there too (the server's Session._heartbeat_sinks says why).
            traffic = (conn.tcp_bytes_out, self._tcp_bytes_in)
            if conn.tcp is not None and (conn.udp is None
                                         or traffic == self._tcp_bytes_at_heartbeat):
                conn.send_tcp(conn.codec.encode_frame(hb))
            if conn.udp is not None:
                conn.send_udp_packet(hb)
            self._tcp_bytes_at_heartbeat = (conn.tcp_bytes_out, self._tcp_bytes_in)
        return (link.next_deadline(now) - now) / 1e9  # never before now

    def _stream(self, packets: list[Packet | Malformed]) -> None:
        """One TCP read's packets, in order. A ``Value`` that continues its channel's run
        (nearly every one) joins it right here, without ``_dispatch`` and ``_gather``."""
        # inlines: Receiver._dispatch, Receiver._gather
        link = self._conn.link
        assert link is not None
        now = time.monotonic_ns()
        values = False
        for packet in packets:
            if type(packet) is Value:
                values = True
                run = self._runs.get(packet.channel)  # re-read: a dispatch may flush
                if run is not None and packet.seq == run[0] + len(run[2]):
                    run[1].append(packet.stamp_ns)
                    run[2].append(packet.value)
                else:
                    self._gather(packet.channel, packet.seq, [packet.stamp_ns], [packet.value])
            elif isinstance(packet, Malformed):
                log.warning("malformed packet from server: %s", packet.error.reason)
            else:
                self._dispatch(packet)
        if values:
            link.on_receive(now)  # one arrival for the read's values

    def _dispatch(self, packet: Packet) -> None:
        conn = self._conn
        link = conn.link
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
            case Bundle():
                link.on_receive(now)
                self._bundle(packet.parts)
            case Heartbeat():
                link.on_heartbeat(packet, now, time.time_ns())
            case TopicAck() | TopicError():
                link.on_receive(now)
                conn.requests.answer(packet)
            case Error():
                link.on_receive(now)
                log.warning("server reported: %s (code %d, channel %s)", packet.reason,
                            packet.code, packet.channel)
                conn.requests.refused(packet)
                if conn.on_error is not None:
                    conn.on_error(packet)
            case Stats():
                conn.requests.answer_stats(packet)
            case Credit():
                link.on_receive(now)
                if conn.on_credit is not None:
                    conn.on_credit(packet.channel, packet.limit)
            case LossReport():
                link.on_receive(now)
                if conn.on_loss is not None:
                    conn.on_loss(packet)
            case ServiceResult() | ServiceRequest() | GoalResult() | RosLoss():
                link.on_receive(now)
                self._service_packet(packet)
            case ConnectError():
                conn.end_session(f"server ended the session: {packet.reason}", conn.generation)
            case Disconnect():
                conn.end_session(f"server closed the session: {packet.reason or 'no reason'}",
                                 conn.generation)
            case _:
                link.on_receive(now)

    def _service_packet(self, packet: ServiceResult | ServiceRequest | GoalResult | RosLoss
                        ) -> None:
        """Services, goals and ROS-side loss (client/session/services.py,
        client/bridge.py)."""
        conn = self._conn
        if isinstance(packet, ServiceResult):
            conn.services.on_result(packet)
        elif isinstance(packet, ServiceRequest):
            conn.services.on_request(packet)
        elif isinstance(packet, GoalResult):
            self._flush_values()  # the goal's feedback before its end
            conn.services.on_goal_result(packet)
        elif conn.on_ros_loss is not None:
            conn.on_ros_loss(packet.channel, packet.ros_lost)

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
            on_values = self._conn.on_values
            if on_values is not None:
                for channel, (first_seq, stamps, values) in runs.items():
                    on_values(channel, first_seq, stamps, values)

    def _deliver(self, channel: int, run: tuple[int, list[int], list[object]]) -> None:
        on_values = self._conn.on_values
        if on_values is not None:
            on_values(channel, run[0], run[1], run[2])
