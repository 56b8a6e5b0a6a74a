"""The client's half of the handshake: sockets, hello, PSK challenge, answer.

Functions of one :class:`~rlbridge.csp.connection.Connection`, run in the thread that opens a
session (``open`` or the reconnect supervisor). They store each socket on the connection as
soon as it exists, so :meth:`~rlbridge.csp.connection.Connection.close` from another thread
can shut it down and abort a handshake blocked in ``connect``, ``recv`` or ``select``.
With a pre-shared key (:mod:`rlbridge.csp.auth`) the server's challenge is answered on the
way; the connection seals its codec once the ack has arrived.
"""

from __future__ import annotations

import errno
import os
import select
import socket
import time
from typing import TYPE_CHECKING

from rlbridge.csp.auth import refused
from rlbridge.csp.tls_client import plaintext_refused, start_tls
from rlbridge.errors import ConnectionClosed, ConnectionFailed, TlsFailed
from rlbridge.sockbuf import request_buffer
from rlbridge.wire import (
    AuthChallenge,
    ConnectAck,
    ConnectError,
    ErrorCode,
    FrameDecoder,
    Heartbeat,
    Hello,
    Malformed,
    Packet,
    RemoteProtocolError,
)
from rlbridge.wire.records import RecordOpener, SealedStreamDecoder, stream_sealers

if TYPE_CHECKING:
    from rlbridge.csp.session_owner import SessionOwner

#: Bytes of queued datagrams the client's UDP socket asks the kernel for.
UDP_RECEIVE_BUFFER = 4 << 20

#: Packets that arrived with the ack, for the receive thread to handle first.
Leftover = list[Packet | Malformed]


def open_tcp(conn: SessionOwner, hello: Hello,
             wake: socket.socket) -> tuple[ConnectAck, Leftover]:
    """Handshake over TCP (control) and then the UDP socket for the values sent by UDP."""
    conn.tcp = sock = connect_tcp(conn, wake)
    if conn.nodelay:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    where = f"{conn.host}:{conn.port}"
    if conn.tls is not None:
        conn.guard.tls = start_tls(conn, sock, wake)
    conn.send_tcp(conn.codec.encode_frame(hello))
    sealed = conn.auth is not None and conn.tls is None  # records after the proof
    decoder = SealedStreamDecoder(conn.codec) if sealed else FrameDecoder(conn.codec)
    conn.guard.decoder = decoder
    deadline = time.monotonic() + conn.timeout
    while True:
        sock.settimeout(max(0.01, deadline - time.monotonic()))
        try:
            data = sock.recv(65536)
        except TimeoutError:
            raise ConnectionFailed(f"no answer from {where} within {conn.timeout} s") from None
        if not data:
            raise ConnectionFailed(f"{where} closed the connection")
        if conn.tls is None and (wants_tls := plaintext_refused(data, where)) is not None:
            raise wants_tls
        try:
            packets = decoder.feed(conn.tcp_received(data))
        except RemoteProtocolError as exc:
            if conn.tls is not None:
                raise TlsFailed(f"{where} refused the TLS session: {exc.reason}") from None
            raise ConnectionFailed(f"{where} sent something that is not rlbridge protocol: "
                                   f"{exc.reason}") from None
        if conn.auth is not None and packets and isinstance(packets[0], AuthChallenge):
            proof = conn.auth.answer(
                packets[0], lambda p: conn.send_tcp(conn.codec.encode_frame(p)))
            conn.send_tcp(conn.codec.encode_frame(proof))
            if isinstance(decoder, SealedStreamDecoder):
                seal_stream(conn, decoder)
            packets = packets[1:]
        if packets:
            first = packets[0]
            break
    sock.settimeout(None)
    if isinstance(first, Malformed):
        raise ConnectionFailed(f"server sent an invalid packet: {first.error.reason}")
    ack = expect_ack(first)
    if isinstance(decoder, SealedStreamDecoder) and decoder.installed and not decoder.records:
        from rlbridge.errors import AuthRefused

        raise AuthRefused(int(ErrorCode.AUTH_FAILED), f"{where} sent the session's ack "
                          "unsealed: not the server that proved the key (someone in between)")
    leftover = packets[1:]
    conn.udp = udp_socket(conn.host, conn.port)
    return ack, leftover


def seal_stream(conn: SessionOwner, decoder: SealedStreamDecoder) -> None:
    """After our proof: records both ways (the ack is the server's first sealed record)."""
    assert conn.auth is not None
    assert conn.auth.keys is not None
    sealer, opener_key = stream_sealers(conn.auth.keys, server=False)
    decoder.install(RecordOpener(opener_key), strict=False)
    with conn.tcp_lock:
        conn.guard.sealer = sealer


def open_udp(conn: SessionOwner, hello: Hello) -> tuple[ConnectAck, Leftover]:
    """Handshake over UDP only: the hello is repeated until an answer or the deadline."""
    conn.udp = sock = udp_socket(conn.host, conn.port)
    datagram = conn.codec.encode_datagram(hello, 0)
    deadline = time.monotonic() + conn.timeout
    while time.monotonic() < deadline and not conn.closed.is_set():
        sock.send(datagram)
        ready, _, _ = select.select([sock], [], [], 0.2)
        if ready:
            try:
                data = sock.recv(65536)
                packet = (conn.auth.decode(conn.codec, data) if conn.auth is not None
                          else conn.codec.decode_datagram(data)[2])
            except RemoteProtocolError:
                continue  # not an answer to us (or forged): keep asking until the deadline
            if isinstance(packet, AuthChallenge) and conn.auth is not None:
                datagram = conn.codec.encode_datagram(conn.auth.answer(packet, sock), 0)
                continue
            if isinstance(packet, Heartbeat):  # a live session whose ack was lost: ask again
                continue
            return expect_ack(packet), []
    raise ConnectionFailed(
        f"no answer over UDP from {conn.host}:{conn.port} within {conn.timeout} s")


def connect_tcp(conn: SessionOwner, wake: socket.socket) -> socket.socket:
    """``connect`` that ``close`` can interrupt through ``wake`` (a dropped SYN would wait
    ``timeout``)."""
    family, kind, proto, _name, address = socket.getaddrinfo(
        conn.host, conn.port, type=socket.SOCK_STREAM)[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setblocking(False)
        err = sock.connect_ex(address)
        if err not in (0, errno.EINPROGRESS):
            raise OSError(err, os.strerror(err))
        ready, writable, _ = select.select([wake], [sock], [], conn.timeout)
        if ready:
            raise ConnectionClosed("connection closed while connecting")
        if not writable:
            raise ConnectionFailed(
                f"no answer from {conn.host}:{conn.port} within {conn.timeout} s")
        err = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if err:
            raise OSError(err, os.strerror(err))
        sock.setblocking(True)
    except BaseException:
        sock.close()
        raise
    return sock


def udp_socket(host: str, port: int) -> socket.socket:
    """A UDP socket connected to the server, with a receive buffer for bursts."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_DGRAM)
    # Room for a burst while the receive thread waits for the GIL (the default ~200 KiB
    # holds under 200 small datagrams); past net.core.rmem_max only with CAP_NET_ADMIN
    # (rlbridge.sockbuf), else capped: the rest are gaps the channels count.
    try:
        request_buffer(sock, "receive", UDP_RECEIVE_BUFFER)
        sock.connect((host, port))
    except BaseException:  # a name that does not resolve: the socket is ours to close
        sock.close()
        raise
    return sock


def expect_ack(packet: Packet) -> ConnectAck:
    """The server's answer to the hello: an ack, or the refusal raised as an exception."""
    if isinstance(packet, ConnectAck):
        return packet
    if isinstance(packet, ConnectError):
        raise refused(packet)
    raise ConnectionFailed(f"server answered the hello with {type(packet).__name__}")
