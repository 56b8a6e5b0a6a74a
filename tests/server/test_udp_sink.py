"""UdpSink's own encodings (its fast paths) send what the codec and the packer would."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Iterator

import pytest

from rlbridge.server.sinks import UdpSink
from rlbridge.wire import Batch, Error, Packet, PacketCodec, Value
from rlbridge.wire.auth import SealedCodec
from rlbridge.wire.bundle import DatagramPacker

TOKEN = 0x0123456789ABCDEF
SEND_KEY, RECEIVE_KEY = bytes(range(32)), bytes(range(32, 64))


def _codec(sealed: bool) -> PacketCodec:
    """A fresh codec: sealed ones start their counters at 1, so two seal the same bytes."""
    return SealedCodec(SEND_KEY, RECEIVE_KEY) if sealed else PacketCodec()


@pytest.fixture
def rx() -> Iterator[socket.socket]:
    """Where the sink sends: a bound UDP socket, read with a timeout."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.settimeout(10.0)
        yield sock


async def _transport() -> asyncio.DatagramTransport:
    transport, _ = await asyncio.get_running_loop().create_datagram_endpoint(
        asyncio.DatagramProtocol, local_addr=("127.0.0.1", 0))
    return transport


def test_datagrams_are_byte_for_byte_the_codecs(rx: socket.socket) -> None:
    codec = PacketCodec()
    token = TOKEN
    packets: list[Packet] = [Value(3, 7, 123, 2.5), Batch(4, 9, [1, 2], [1.0, -2.0]),
                             Error(5, "why", 3), Value(1, 0, 0, {"data": [1, 2, 3]})]

    async def send_all() -> None:
        transport = await _transport()
        try:
            sink = UdpSink(transport, codec, token, rx.getsockname(), 1400)
            for p in packets:
                assert sink.send(p, data=True)
        finally:
            transport.close()

    asyncio.run(send_all())
    got = [rx.recv(65536) for _ in packets]
    assert got == [codec.encode_datagram(p, token) for p in packets]
    assert [codec.decode_datagram(d) for d in got] == [(0, token, p) for p in packets]


def _reference(codec: PacketCodec, token: int, budget: int,
               rounds: list[list[Packet]]) -> list[bytes]:
    """What the packer makes of ``rounds`` (one loop iteration each), control packets in order."""
    out: list[bytes] = []
    packer = DatagramPacker(codec, token, budget, out.append)
    for packets in rounds:
        for p in packets:
            if isinstance(p, Value | Batch):
                packer.add(p)
            else:
                packer.flush()
                out.append(codec.encode_datagram(p, token))
        packer.flush()
    return out


#: Twelve numbers that make a 255-byte bundle datagram.
TWELVE: list[Packet] = [Value(c, 300, 70000, 1.0 + c) for c in range(12)]


@pytest.mark.parametrize("rounds", [
    pytest.param([[Value(c, 7, 123, 0.5 * c) for c in range(10)]], id="ten-numbers"),
    pytest.param([[Value(1, 0, 1, 1.0)]], id="one-number"),
    pytest.param([[Value(1, 0, 1, 1.0), Value(2, 0, 1, "text"), Value(3, 0, 1, 3)]],
                 id="a-string-between"),
    pytest.param([[Value(1, 0, 1, "first"), Value(2, 0, 1, 2.0), Value(3, 0, 1, 3.0)],
                  [Value(1, 1, 1, 1.0), Value(2, 1, 1, 2.0)]], id="a-string-first"),
    pytest.param([[Value(1, 0, 1, True), Error(5, "why", 1), Value(2, 0, 1, 2.0),
                   Value(3, 0, 1, -3)]], id="control-between"),
    pytest.param([[Value(c, 2**40, 2**62, 1.0 + c) for c in range(40)]], id="over-budget"),
    pytest.param([[Value(c, 0, 0, float(c)) for c in range(20)],
                  [Batch(1, 1, [1, 2], [1.0, 2.0]), Value(2, 1, 0, 3.0)]], id="two-rounds"),
    # Bundles of 254, 255 and 256 bytes: the packer reserves an array16 header (two bytes
    # more than these 12 parts' fixarray), so only the first leaves as one datagram.
    pytest.param([[Value(0, 200, 70000, 1.0), *TWELVE[1:]]], id="254-bytes"),
    pytest.param([TWELVE], id="255-bytes"),
    pytest.param([[Value(200, 300, 70000, 1.0), *TWELVE[1:]]], id="256-bytes"),
])
@pytest.mark.parametrize("sealed", [False, True], ids=["plain", "sealed"])
def test_corked_values_are_byte_for_byte_the_packers(rx: socket.socket,
                                                     rounds: list[list[Packet]],
                                                     sealed: bool) -> None:
    """Numbers gathered unencoded and encoded (and sealed) as one bundle leave as the packer's
    datagrams."""
    codec = _codec(sealed)
    token, budget = TOKEN, 256

    async def send_all() -> UdpSink:
        transport = await _transport()
        try:
            sink = UdpSink(transport, codec, token, rx.getsockname(), budget,
                           asyncio.get_running_loop())
            sink.bundles = True
            for packets in rounds:
                for p in packets:
                    assert sink.send(p, data=isinstance(p, Value | Batch))
                await asyncio.sleep(0)  # the iteration ends: the corked values leave
                await asyncio.sleep(0)
            return sink
        finally:
            transport.close()

    expected = _reference(_codec(sealed), token, budget, rounds)
    sink = asyncio.run(send_all())
    got = [rx.recv(65536) for _ in expected]
    assert got == expected
    if sealed:  # and they open, in order, under the receiving side's key
        opener = SealedCodec(RECEIVE_KEY, SEND_KEY)
        assert [opener.decode_datagram(d)[1] for d in got] == [token] * len(got)
    assert sink.datagrams == len(expected) - sum(
        not isinstance(p, Value | Batch) for r in rounds for p in r)
    assert sink.dropped == 0
