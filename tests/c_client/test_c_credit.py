"""Credit on a flow-controlled TCP publish channel (protocol.md 10.5), from the server's side.

A scripted server (real sockets, the SDK's codec) answers ``rlb_pub --tcp`` with a first
credit of 5: the client sends values 0..4 and holds the rest; a ``Credit`` of 20 releases them,
in order, each once. The real server grants 65,536 values at once, too many to see this.
"""

from __future__ import annotations

import socket
import struct
import subprocess
import time
from pathlib import Path

from rlbridge.wire import PacketCodec
from rlbridge.wire.packets import (
    Batch,
    ConnectAck,
    Credit,
    Disconnect,
    Heartbeat,
    Hello,
    Limits,
    Packet,
    TopicAck,
    TopicConnect,
    Value,
)

CODEC = PacketCodec()


class Peer:
    """One TCP connection of the scripted server: frames in, frames out."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.buf = b""

    def send(self, packet: Packet) -> None:
        self.sock.sendall(CODEC.encode_frame(packet))

    def read(self, timeout: float) -> Packet | None:
        """The next packet, or None when nothing came within ``timeout``."""
        deadline = time.monotonic() + timeout
        while True:
            if len(self.buf) >= 8:
                (length,) = struct.unpack(">I", self.buf[4:8])
                if len(self.buf) >= 8 + length:
                    body, self.buf = self.buf[8:8 + length], self.buf[8 + length:]
                    return CODEC.decode_body(body)
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self.sock.settimeout(left)
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                return None
            if not data:
                return None
            self.buf += data


def _values(packet: Packet) -> list[tuple[int, float]]:
    if isinstance(packet, Value):
        return [(packet.seq, packet.value)]
    if isinstance(packet, Batch):
        return [(packet.first_seq + i, v) for i, v in enumerate(packet.values)]
    return []


def test_rlb_pub_sends_only_what_the_credit_allows(c_build: Path) -> None:
    with socket.socket() as listener, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        listener.bind(("127.0.0.1", 0))
        port = listener.getsockname()[1]
        udp.bind(("127.0.0.1", port))  # the client's heartbeat datagrams land here, unread
        listener.listen(1)
        pub = subprocess.Popen([str(c_build / "rlb_pub"), "127.0.0.1", str(port), "/credit",
                                "20", "1000", "--tcp"], stderr=subprocess.PIPE, text=True)
        try:
            listener.settimeout(30)
            conn, _ = listener.accept()
            with conn:
                peer = Peer(conn)
                assert isinstance(peer.read(30), Hello)
                peer.send(ConnectAck(1, 0x1234, 200, 30000, Limits(1 << 20, 256, 4096)))
                bind = peer.read(30)
                assert isinstance(bind, TopicConnect)
                assert bind.flow  # on for TCP publish channels by default
                peer.send(TopicAck(bind.channel, bind.msg_type, 0.0, None, credit=5))
                got: list[tuple[int, float]] = []
                while len(got) < 5:
                    packet = peer.read(30)
                    assert packet is not None, f"only {got} arrived"
                    got += _values(packet)
                # The loop wrote all 20 long ago; within a second nothing beyond the credit.
                deadline = time.monotonic() + 1.0
                while (left := deadline - time.monotonic()) > 0:
                    packet = peer.read(left)
                    if packet is not None:
                        got += _values(packet)
                assert got == [(i, float(i)) for i in range(5)]
                peer.send(Credit(bind.channel, 20))
                while len(got) < 20:
                    packet = peer.read(30)
                    assert packet is not None, f"only {len(got)} values arrived"
                    assert not isinstance(packet, Disconnect), got
                    got += _values(packet)
                assert got == [(i, float(i)) for i in range(20)]
                while not isinstance(packet, Disconnect):  # rlb_pub flushed, says goodbye
                    packet = peer.read(30)
                    assert packet is None or isinstance(packet, Heartbeat | Disconnect)
                    assert packet is not None, "no goodbye"
            assert pub.wait(timeout=30) == 0, pub.communicate()[1]
        finally:
            if pub.poll() is None:
                pub.kill()
            pub.communicate(timeout=10)
