"""``rlbridge ping``: does a bridge server answer? The health probe for containers and scripts.

One hello, over TCP (or one UDP datagram), and whatever the server answers first: a session
(closed again at once), a key challenge, or a refusal. Each of those proves the server is up
and serving its protocol, so each counts as an answer; only silence, a closed port or bytes
that are not rlbridge's do not. No key is needed, so a probe works against a server that
requires one (it stops at the challenge and never opens a session).
"""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass

from rlbridge.server.notices import PROBE_NAME
from rlbridge.wire import (
    PROTOCOL_VERSION,
    AuthChallenge,
    ConnectAck,
    ConnectError,
    Disconnect,
    FrameDecoder,
    Hello,
    Malformed,
    Packet,
    PacketCodec,
    RlbridgeError,
)


class NoAnswer(RlbridgeError):
    """The server did not answer the probe; the message says what happened instead."""


@dataclass(frozen=True)
class Answer:
    """What the server said and how long it took."""

    transport: str
    seconds: float
    said: str


def _said(packet: Packet) -> str:
    match packet:
        case ConnectAck():
            return f"session {packet.session} opened (heartbeat {packet.heartbeat_ms} ms)"
        case AuthChallenge():
            return "asked for its pre-shared key"
        case ConnectError():
            return f"refused the probe: {packet.reason}"
        case _:
            return f"answered {type(packet).__name__}"


def ping(host: str, port: int, transport: str = "tcp", timeout: float = 2.0) -> Answer:
    """Send one hello to ``host:port``; :class:`Answer`, or :class:`NoAnswer` saying why."""
    codec = PacketCodec()
    hello = Hello(PROTOCOL_VERSION, PROBE_NAME)
    where = f"{host}:{port} ({transport.upper()})"
    start = time.monotonic()
    try:
        if transport == "udp":
            packet = _udp(codec, hello, host, port, timeout)
        else:
            packet = _tcp(codec, hello, host, port, timeout)
    except TimeoutError:
        raise NoAnswer(f"no answer from {where} within {timeout:g} s") from None
    except OSError as exc:
        raise NoAnswer(f"cannot reach {where}: {exc.strerror or exc}") from None
    return Answer(transport, time.monotonic() - start, _said(packet))


def _tcp(codec: PacketCodec, hello: Hello, host: str, port: int, timeout: float) -> Packet:
    deadline = time.monotonic() + timeout
    with socket.create_connection((host, port), timeout=timeout) as sock:
        sock.sendall(codec.encode_frame(hello))
        decoder = FrameDecoder(codec)
        while True:
            sock.settimeout(max(0.001, deadline - time.monotonic()))
            data = sock.recv(1 << 16)
            if not data:
                raise NoAnswer(f"{host}:{port} (TCP) closed the connection without answering")
            try:
                packets = decoder.feed(data)
            except RlbridgeError:
                raise NoAnswer(f"{host}:{port} (TCP) answered, but not in the rlbridge "
                               "protocol (another service on that port?)") from None
            for packet in packets:
                if isinstance(packet, Malformed):
                    raise NoAnswer(f"{host}:{port} (TCP) sent a packet that does not decode")
                if isinstance(packet, ConnectAck):
                    sock.sendall(codec.encode_frame(Disconnect(0, "ping done")))
                return packet


def _udp(codec: PacketCodec, hello: Hello, host: str, port: int, timeout: float) -> Packet:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET,
                       socket.SOCK_DGRAM) as sock:
        sock.settimeout(timeout)
        sock.connect((host, port))
        sock.send(codec.encode_datagram(hello, 0))
        try:
            data = sock.recv(1 << 16)
        except ConnectionRefusedError:
            raise NoAnswer(f"nothing listens on {host}:{port} (UDP)") from None
        try:
            _flags, _token, packet = codec.decode_datagram(data)
        except RlbridgeError:
            raise NoAnswer(f"{host}:{port} (UDP) answered, but not in the rlbridge "
                           "protocol") from None
        if isinstance(packet, ConnectAck):
            sock.send(codec.encode_datagram(Disconnect(0, "ping done"), packet.token))
        return packet
