"""UdpSink's own encodings (its fast paths) send what the codec and the packer would."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

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


scalars = st.one_of(st.floats(allow_nan=False), st.integers(-(2**63), 2**63 - 1),
                    st.booleans(), st.text(max_size=20))


@st.composite
def sink_packets(draw: st.DrawFn) -> Packet:
    kind = draw(st.integers(0, 5))
    channel, seq = draw(st.integers(0, 300)), draw(st.integers(0, 2**40))
    if kind == 0:
        return Error(draw(st.integers(1, 9)), "why", channel)
    if kind == 1:
        vals = draw(st.lists(scalars, min_size=1, max_size=4))
        return Batch(channel, seq, [draw(st.integers(0, 2**62))] * len(vals), vals)
    return Value(channel, seq, draw(st.integers(0, 2**62)), draw(scalars))


@pytest.mark.parity("rlbridge.server.sinks.UdpSink.send")
@settings(deadline=None, max_examples=60, suppress_health_check=[HealthCheck.too_slow])
@given(rounds=st.lists(st.lists(sink_packets(), max_size=12), min_size=1, max_size=3),
       sealed=st.booleans(), budget=st.sampled_from([256, 1400]))
def test_any_rounds_leave_as_the_codecs_and_the_packers_datagrams(
        rounds: list[list[Packet]], sealed: bool, budget: int) -> None:
    """The sink's own encodings (a header packed once, numbers corked unencoded) against
    the codec's ``encode_datagram`` and the packer's ``add``, for any loop iterations."""
    codec = _codec(sealed)
    expected = _reference(_codec(sealed), TOKEN, budget, rounds)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        rx.settimeout(10.0)

        async def send_all() -> None:
            transport = await _transport()
            try:
                sink = UdpSink(transport, codec, TOKEN, rx.getsockname(), budget,
                               asyncio.get_running_loop())
                sink.bundles = True
                for packets in rounds:
                    for p in packets:
                        assert sink.send(p, data=isinstance(p, Value | Batch))
                    await asyncio.sleep(0)  # the iteration ends: the corked values leave
                    await asyncio.sleep(0)
            finally:
                transport.close()

        asyncio.run(send_all())
        got = [rx.recv(65536) for _ in expected]
        rx.setblocking(False)
        with pytest.raises(BlockingIOError):  # and nothing more
            rx.recv(65536)
    assert got == expected
