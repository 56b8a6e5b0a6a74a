"""A bad header after good frames in one TCP write: the frames run first, then the error.

The server answers a header that loses the framing (Error + Disconnect, or a ConnectError
before a session exists) only after it has handled every frame that came before it in the
same read, in order: values published, requests answered, as if the bytes had come in
separate reads. A live server on loopback with the in-process bus, spoken to by raw sockets;
the bus's subscriber is in this process, so what reached the middleware is read directly.
Delivery on the bus is synchronous, inside the server's handling of the frame, so the values
are there once the error has arrived.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from rlbridge import ErrorCode
from rlbridge.adapters.base import QoS
from rlbridge.adapters.inproc import InProcessBus
from rlbridge.server import ServerThread
from rlbridge.wire import (
    FRAME_HEADER,
    MAGIC,
    PROTOCOL_VERSION,
    ConnectAck,
    Disconnect,
    Error,
    Heartbeat,
    Hello,
    Packet,
    PacketCodec,
    Stats,
    TopicAck,
    TopicConnect,
    Value,
)

F64 = "std_msgs/msg/Float64"
TOPIC = "/faults/run"
MAX_PACKET = 4096
CODEC = PacketCodec()
VALUES = [0.5, 1.5, 2.5, 3.5, 4.5]

#: Headers that lose the framing: (header, code the server answers, phrase of its reason).
BAD_HEADERS = [
    (FRAME_HEADER.pack(b"XX", PROTOCOL_VERSION, 0, 2) + b"\x91\x0a", ErrorCode.MALFORMED,
     "bad magic b'XX'"),
    (FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION + 1, 0, 2), ErrorCode.UNSUPPORTED_VERSION,
     "not supported"),
    (FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0x01, 2), ErrorCode.MALFORMED, "flags bit 0"),
    (FRAME_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, MAX_PACKET + 1), ErrorCode.TOO_LARGE,
     f"exceeds the limit of {MAX_PACKET} bytes"),
]
BAD_IDS = ["magic", "version", "sealed-flag", "too-large"]


def published(srv: ServerThread, topic: str = TOPIC) -> list[Any]:
    """Every value ``srv`` publishes on ``topic`` from now on, in order: a subscriber on its
    in-process bus, whose delivery is synchronous, on the server's loop."""
    registry = srv.server.registry
    assert registry is not None
    bus = registry.ctx.adapter
    assert isinstance(bus, InProcessBus)
    got: list[Any] = []
    bus.subscribe(topic, F64, "data", QoS(), got.extend)
    return got


def counter(srv: ServerThread, name: str) -> int:
    registry = srv.server.registry
    assert registry is not None
    return int(registry.ctx.counters.get(name, 0))


@pytest.fixture
def small_server(make_server: Callable[..., ServerThread]) -> ServerThread:
    """A server whose frame limit a short header can exceed."""
    return make_server(max_packet=MAX_PACKET)


def frames(*packets: Packet) -> bytes:
    buf = bytearray()
    for packet in packets:
        CODEC.encode_frame_into(packet, buf)
    return bytes(buf)


def values() -> list[Packet]:
    return [Value(1, seq, 0, v) for seq, v in enumerate(VALUES)]


def ends_with_error(got: list[Packet], code: ErrorCode, phrase: str) -> list[Packet]:
    """``Error(code)`` naming ``phrase``, then ``Disconnect(code)``, last; what came before
    (heartbeats left out: the server sends one right after its ConnectAck)."""
    got = [p for p in got if not isinstance(p, Heartbeat)]
    assert len(got) >= 2, got
    error, goodbye = got[-2:]
    assert isinstance(error, Error), got
    assert (error.code, phrase in error.reason) == (code, True), error
    assert isinstance(goodbye, Disconnect), got
    assert goodbye.code == code
    return got[:-2]


@pytest.mark.parametrize(("bad", "code", "phrase"), BAD_HEADERS, ids=BAD_IDS)
def test_values_before_a_bad_header_in_one_write_are_published_then_it_is_answered(
        small_server: ServerThread, raw_tcp: Callable[..., Any], bad: bytes, code: ErrorCode,
        phrase: str) -> None:
    client = raw_tcp(small_server.port)
    on_bus = published(small_server)
    client.hello("faulty")
    client.send(TopicConnect(1, "publish", TOPIC, F64, transport="tcp"))
    client.expect(TopicAck)
    # One write: five values, a request the server answers, then the bad header.
    client.send_bytes(frames(*values(), Stats()) + bad)
    before = ends_with_error(client.wait_closed(), code, phrase)
    assert on_bus == VALUES
    assert [type(p) for p in before] == [Stats], before  # answered before the error
    assert counter(small_server, "malformed") == 1


def test_a_whole_session_and_a_bad_header_in_one_write(small_server: ServerThread,
                                                       raw_tcp: Callable[..., Any]) -> None:
    """The hello, the binding, the values and the bad header in one write: the session opens,
    the values are published, and only then is the stream refused (inside the session now, so
    Error + Disconnect rather than a ConnectError)."""
    client = raw_tcp(small_server.port)
    on_bus = published(small_server)
    hello = Hello(PROTOCOL_VERSION, "all-at-once")
    bind = TopicConnect(1, "publish", TOPIC, F64, transport="tcp")
    client.send_bytes(frames(hello, bind, *values()) + BAD_HEADERS[0][0])
    before = ends_with_error(client.wait_closed(), ErrorCode.MALFORMED, "bad magic")
    assert [type(p) for p in before] == [ConnectAck, TopicAck], before
    assert on_bus == VALUES


def test_nothing_after_a_goodbye_in_the_same_write_is_answered(
        small_server: ServerThread, raw_tcp: Callable[..., Any]) -> None:
    """A Disconnect ends the session where it stands: the bad header after it in the same
    read is never read, as it would not be had it come in a later read."""
    client = raw_tcp(small_server.port)
    on_bus = published(small_server)
    client.hello("leaver")
    client.send(TopicConnect(1, "publish", TOPIC, F64, transport="tcp"))
    client.expect(TopicAck)
    client.send_bytes(frames(*values(), Disconnect(0, "bye")) + BAD_HEADERS[0][0])
    assert [p for p in client.wait_closed() if not isinstance(p, Heartbeat)] == []
    assert on_bus == VALUES
    assert counter(small_server, "malformed") == 0
