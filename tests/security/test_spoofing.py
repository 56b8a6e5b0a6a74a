"""An on-path attacker, for real: raw sockets (root) sniff loopback UDP and inject datagrams
with the server's source address and port into a client, and the client's into the server.

Without a key a sniffed token is enough to inject values (what the token does not stop, see
docs/security.md); with a key the same forged and replayed datagrams are dropped and counted.
"""

from __future__ import annotations

import os
import select
import socket
import struct
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from rlbridge import Psk, Tuning
from rlbridge.client.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.wire import PROTOCOL_VERSION, Hello, PacketCodec, Value
from rlbridge.wire.codec import FLAG_MAC, peek_header
from waiting import wait_until

F64 = "std_msgs/msg/Float64"
KEY = bytes(range(32))
WAIT = 10.0
UDP_HEADER = struct.Struct(">HHHH")


class Wire:
    """A raw UDP socket on the host: every loopback UDP datagram in, any source port out."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_UDP)

    def inject(self, src_port: int, dst_port: int, payload: bytes) -> None:
        # Checksum 0 means "none" on IPv4; the kernel writes the IP header (source 127.0.0.1).
        header = UDP_HEADER.pack(src_port, dst_port, UDP_HEADER.size + len(payload), 0)
        self.sock.sendto(header + payload, ("127.0.0.1", 0))

    def sniff(self, src_port: int, dst_port: int, want: Callable[[bytes], bool],
              timeout: float = WAIT) -> bytes:
        """The payload of the next datagram ``src_port -> dst_port`` that ``want`` accepts."""
        def wanted() -> bytes | None:  # (a datagram of the protocol is never empty)
            if not select.select([self.sock], [], [], 0.1)[0]:
                return None
            packet = self.sock.recv(65536)
            ihl = (packet[0] & 0x0F) * 4
            src, dst, _length, _sum = UDP_HEADER.unpack_from(packet, ihl)
            payload = packet[ihl + UDP_HEADER.size :]
            return payload if (src, dst) == (src_port, dst_port) and want(payload) else None

        payload: bytes = wait_until(wanted, f"a datagram {src_port} -> {dst_port} the test wants",
                                    timeout=timeout, interval=0)
        return payload

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def wire() -> Iterator[Wire]:
    if os.geteuid() != 0:
        pytest.skip("raw sockets need root")
    try:
        w = Wire()
    except PermissionError:
        pytest.skip("raw sockets not permitted here")
    yield w
    w.close()


def _ports(bridge: Bridge, server: ServerThread) -> tuple[int, int]:
    udp = bridge._conn.udp
    assert udp is not None
    return server.port, udp.getsockname()[1]


def test_without_a_key_a_sniffed_token_lets_an_attacker_inject(
        server: ServerThread, wire: Wire) -> None:
    with Bridge.connect("127.0.0.1", server.port, timeout=WAIT) as bridge:
        inbox = bridge.subscribe("/victim", F64, transport="udp", blocking=True,
                                 buffer_size=16)
        server_port, client_port = _ports(bridge, server)
        seen = wire.sniff(server_port, client_port, lambda d: True)  # e.g. a heartbeat
        _flags, token = peek_header(seen)
        codec = PacketCodec()
        wire.inject(server_port, client_port, codec.encode_datagram(Value(1, 0, 0, 1.0), 1))
        wire.inject(server_port, client_port, codec.encode_datagram(Value(1, 1, 0, 66.6), token))
        assert inbox.read(timeout=WAIT) == 66.6  # the forgery is delivered
        assert bridge._conn.datagrams_dropped["bad_token"] == 1  # only the blind guess fails


def test_with_a_key_forged_and_replayed_datagrams_are_dropped_both_ways(
        make_server: Callable[..., ServerThread], tmp_path: Path, wire: Wire) -> None:
    keys = tmp_path / "keys"
    keys.write_text(KEY.hex())
    srv = make_server(psk_file=keys)
    with Bridge.connect("127.0.0.1", srv.port, security=Psk(key=KEY), timeout=WAIT) as bridge:
        inbox = bridge.subscribe("/victim", F64, transport="udp", blocking=True,
                                 buffer_size=16)
        server_port, client_port = _ports(bridge, srv)

        def sealed(d: bytes) -> bool:
            return bool(peek_header(d)[0] & FLAG_MAC)

        to_client = wire.sniff(server_port, client_port, sealed)
        to_server = wire.sniff(client_port, server_port, sealed)
        token = peek_header(to_client)[1]
        forged = PacketCodec().encode_datagram(Value(1, 0, 0, 66.6), token)
        tampered = bytearray(to_client)
        tampered[-1] ^= 0x01
        for payload in (to_client, forged, bytes(tampered)):  # replayed, unsealed, bad MAC
            wire.inject(server_port, client_port, payload)
        for payload in (to_server, forged):
            wire.inject(client_port, server_port, payload)
        conn = bridge._conn
        wait_until(lambda: sum(conn.datagrams_dropped.values()) >= 3, "three dropped datagrams")
        assert conn.datagrams_dropped == {"replayed": 1, "unsealed": 1, "bad_mac": 1}
        server_counts = bridge.server_stats()["server"]
        assert server_counts["udp_replayed"] == 1
        assert server_counts["udp_unsealed"] == 1
        # The genuine session still works after the attack.
        out = bridge.publish("/victim", F64, transport="udp")
        out.write(2.5)
        assert inbox.read(timeout=WAIT) == 2.5


def test_spoofed_hellos_cannot_grow_the_pending_handshakes(
        make_server: Callable[..., ServerThread], tmp_path: Path, wire: Wire) -> None:
    """300 key hellos from forged source ports: at most 256 challenges remembered."""
    keys = tmp_path / "keys"
    keys.write_text(KEY.hex())
    srv = make_server(psk_file=keys)
    codec = PacketCodec()
    hello = codec.encode_datagram(Hello(PROTOCOL_VERSION, "flood", b"n" * 16), 0)
    for port in range(20000, 20300):
        wire.inject(port, srv.port, hello)
    with Bridge.connect("127.0.0.1", srv.port, security=Psk(key=KEY),
                        tuning=Tuning(control="udp"), timeout=WAIT) as bridge:
        counts = bridge.server_stats()["server"]
    assert counts["udp_handshakes_evicted"] >= 300 - 256
    assert counts["sessions_opened"] == 1
