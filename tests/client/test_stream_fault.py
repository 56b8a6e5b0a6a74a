"""A server stream that breaks mid-read: the values before the bad header still arrive.

The SDK decodes a TCP read in one go; a header that loses the framing ends the session, but
what came complete before it in the same read is the server's data all the same.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator

import pytest

from rlbridge import LinkState
from rlbridge.client.bridge import Bridge
from rlbridge.wire import (
    ConnectAck,
    FrameDecoder,
    Hello,
    Limits,
    PacketCodec,
    TopicAck,
    TopicConnect,
    Value,
)
from waiting import wait_until

F64 = "std_msgs/msg/Float64"
WAIT = 10.0
BAD_HEADER = b"XX\x01\x00\x00\x00\x00\x10"  # wrong magic: the framing is lost here


class BreakingServer:
    """Answers one SDK's hello and topic-connect, then sends values and a bad header in one
    ``sendall``."""

    def __init__(self, values: list[float]) -> None:
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(1)
        self.port: int = self.listener.getsockname()[1]
        self.values = values
        self.codec = PacketCodec()
        self.conn: socket.socket | None = None
        self.sent = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        self.listener.settimeout(WAIT)
        conn, _ = self.listener.accept()
        self.conn = conn
        conn.settimeout(WAIT)
        decoder = FrameDecoder(self.codec)
        while not self.sent.is_set():
            for packet in decoder.feed(conn.recv(4096)):
                if isinstance(packet, Hello):
                    conn.sendall(self.codec.encode_frame(
                        ConnectAck(1, 77, 100, 60_000, Limits(1 << 16, 16, 8))))
                elif isinstance(packet, TopicConnect):
                    burst = self.codec.encode_frame(
                        TopicAck(packet.channel, packet.msg_type, ""))
                    burst += b"".join(
                        self.codec.encode_frame(Value(packet.channel, seq, 0, v))
                        for seq, v in enumerate(self.values))
                    conn.sendall(burst + BAD_HEADER)
                    self.sent.set()

    def close(self) -> None:
        self._thread.join(WAIT)
        if self.conn is not None:
            self.conn.close()
        self.listener.close()


@pytest.fixture
def breaking_server() -> Iterator[BreakingServer]:
    srv = BreakingServer([1.0, 2.0, 3.0])
    yield srv
    srv.close()


def test_values_before_a_bad_header_in_the_same_read_are_delivered(
        breaking_server: BreakingServer) -> None:
    bridge = Bridge.connect("127.0.0.1", breaking_server.port, reconnect=False, timeout=WAIT)
    try:
        inbox = bridge.subscribe("/broken", F64, transport="tcp", blocking=True,
                                 buffer_size=16)
        wait_until(lambda: bridge.link_state is not LinkState.CONNECTED,
                   "the session to end on the bad header", timeout=WAIT)
        got = [inbox.read(timeout=WAIT) for _ in breaking_server.values]
    finally:
        bridge.close()
    assert got == breaking_server.values
