"""Bundles on a live server: one datagram per send round, each way, counted on a real socket.

The SDK talks to the server through a UDP relay on loopback that forwards every datagram and
keeps a copy, so the tests count what really crossed the wire (protocol.md 6.16). A UDP-only
session (``control="udp"``) keeps every packet of the session on the relayed socket.
"""

from __future__ import annotations

import select
import socket
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from rlbridge import Policy, Psk, Tuning
from rlbridge.csp.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.wire import Batch, Bundle, PacketCodec, Value
from rlbridge.wire.codec import FLAG_BUNDLES, FLAG_MAC, peek_header

F64 = "std_msgs/msg/Float64"
CHANNELS = 10
KEY = bytes(range(32))


class UdpRelay:
    """Forwards datagrams between one client and a server, keeping a copy of each.

    ``up`` holds what the client sent, ``down`` what the server sent, in order. One socket:
    the server sees the relay as the client. Stopped (and joined) by ``close``.
    """

    def __init__(self, server_port: int) -> None:
        self._server = ("127.0.0.1", server_port)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self.port: int = self._sock.getsockname()[1]
        self._client: tuple[str, int] | None = None
        self.up: list[bytes] = []
        self.down: list[bytes] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="test-relay", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._sock], [], [], 0.05)
            if not ready:
                continue
            data, addr = self._sock.recvfrom(65536)
            if addr == self._server:
                self.down.append(data)
                if self._client is not None:
                    self._sock.sendto(data, self._client)
            else:
                self._client = addr
                self.up.append(data)
                self._sock.sendto(data, self._server)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._sock.close()


@pytest.fixture
def relay_to() -> Iterator[Callable[[ServerThread], UdpRelay]]:
    relays: list[UdpRelay] = []

    def make(server: ServerThread) -> UdpRelay:
        relay = UdpRelay(server.port)
        relays.append(relay)
        return relay

    yield make
    for relay in relays:
        relay.close()


def value_packets(datagrams: list[bytes]) -> list[Value | Batch | Bundle]:
    """The value-carrying packets among plain datagrams (heartbeats and control left out)."""
    codec = PacketCodec()
    packets = [codec.decode_datagram(d)[2] for d in datagrams]
    return [p for p in packets if isinstance(p, (Value, Batch, Bundle))]


def ten_channels(b: Bridge, tag: str) -> tuple[list[Any], list[Any]]:
    """CHANNELS subscribe and publish channels over UDP, pairwise on the same topics."""
    inboxes = [b.subscribe(f"/bundle/{tag}/c{i}", F64, transport="udp", blocking=True,
                           buffer_size=16) for i in range(CHANNELS)]
    outs = [b.publish(f"/bundle/{tag}/c{i}", F64, transport="udp", through_buffer=True)
            for i in range(CHANNELS)]
    return inboxes, outs


def one_round(b: Bridge, inboxes: list[Any], outs: list[Any], value: float) -> None:
    """A value on every channel, one send round, every value read back."""
    for out in outs:
        out.write(value)
    b.send(wait=True)
    assert [inbox.read(timeout=10) for inbox in inboxes] == [value] * len(inboxes)


def test_ten_udp_channels_one_datagram_per_round_each_way(
        make_server: Callable[..., ServerThread],
        relay_to: Callable[[ServerThread], UdpRelay]) -> None:
    """The SDK bundles its round; the server corks the echoes of one bundle into one."""
    srv = make_server(tcp=False)
    relay = relay_to(srv)
    with Bridge.connect("127.0.0.1", relay.port, tuning=Tuning(control="udp"), timeout=10) as b:
        inboxes, outs = ten_channels(b, "plain")
        # Every datagram with the session's token says it reads bundles (the token-0
        # handshake carries flags 0x00, protocol.md 3).
        assert all(peek_header(d)[0] & FLAG_BUNDLES for d in relay.up if peek_header(d)[1])
        for round_ in range(3):
            up, down = len(relay.up), len(relay.down)
            one_round(b, inboxes, outs, float(round_))
            for packets in (value_packets(relay.up[up:]), value_packets(relay.down[down:])):
                assert len(packets) == 1, packets
                assert isinstance(packets[0], Bundle)
                assert len({p.channel for p in packets[0].parts}) == CHANNELS


def test_without_bundles_one_datagram_per_channel_each_way(
        make_server: Callable[..., ServerThread],
        relay_to: Callable[[ServerThread], UdpRelay]) -> None:
    """``bundles=False`` (a server older than bundles): the old single packets, both ways."""
    srv = make_server(tcp=False)
    relay = relay_to(srv)
    with Bridge.connect("127.0.0.1", relay.port, tuning=Tuning(control="udp", bundles=False),
                        timeout=10) as b:
        inboxes, outs = ten_channels(b, "single")
        assert not any(peek_header(d)[0] & FLAG_BUNDLES for d in relay.up)
        up, down = len(relay.up), len(relay.down)
        one_round(b, inboxes, outs, 1.0)
        for packets in (value_packets(relay.up[up:]), value_packets(relay.down[down:])):
            assert [type(p) for p in packets] == [Value] * CHANNELS


def test_sealed_session_bundles_too(make_server: Callable[..., ServerThread],
                                    relay_to: Callable[[ServerThread], UdpRelay],
                                    tmp_path: Path) -> None:
    """With keys every datagram is sealed, bundles included, and they verify both ways."""
    keys = tmp_path / "keys"
    keys.write_text(KEY.hex() + "\n")
    srv = make_server(tcp=False, psk_file=keys)
    relay = relay_to(srv)
    with Bridge.connect("127.0.0.1", relay.port, tuning=Tuning(control="udp"), timeout=10,
                        security=Psk(key=KEY)) as b:
        inboxes, outs = ten_channels(b, "sealed")
        up, down = len(relay.up), len(relay.down)
        one_round(b, inboxes, outs, 7.0)
        # Sealed bodies cannot be read here; the sizes tell: a heartbeat is under 100 bytes,
        # ten values bundled are over 200, ten values one per datagram under 100 each.
        for datagrams in (relay.up[up:], relay.down[down:]):
            assert all(peek_header(d)[0] & FLAG_MAC for d in datagrams)
            assert len([d for d in datagrams if len(d) > 200]) == 1
            assert [d for d in datagrams if 100 <= len(d) <= 200] == []


def test_redundant_channels_keep_their_meaning_in_bundles(
        make_server: Callable[..., ServerThread],
        relay_to: Callable[[ServerThread], UdpRelay]) -> None:
    """Each part of a redundant channel repeats its previous k values; each value read once."""
    srv = make_server(tcp=False)
    relay = relay_to(srv)
    with Bridge.connect("127.0.0.1", relay.port, tuning=Tuning(control="udp"), timeout=10) as b:
        inboxes = [b.subscribe(f"/bundle/red/c{i}", F64, transport="udp", blocking=True,
                               buffer_size=16, policy=Policy(redundancy=2)) for i in range(3)]
        outs = [b.publish(f"/bundle/red/c{i}", F64, transport="udp", through_buffer=True,
                          policy=Policy(redundancy=2)) for i in range(3)]
        for round_ in range(4):
            up, down = len(relay.up), len(relay.down)
            one_round(b, inboxes, outs, float(round_))
            for packets in (value_packets(relay.up[up:]), value_packets(relay.down[down:])):
                assert len(packets) == 1
                bundle = packets[0]
                assert isinstance(bundle, Bundle)
                for part in bundle.parts:  # the new value and up to 2 before it
                    values = part.values if isinstance(part, Batch) else [part.value]
                    assert values == [float(v) for v in range(max(0, round_ - 2), round_ + 1)]
        assert [i.duplicates for i in inboxes] == [0 + 1 + 2 + 2] * 3
        assert [i.lost for i in inboxes] == [0] * 3

