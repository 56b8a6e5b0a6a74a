"""UdpSink's own header-and-body encoding (its fast path) sends what the codec would."""

from __future__ import annotations

import asyncio
import socket

from rlbridge.server.sinks import UdpSink
from rlbridge.wire import Batch, Error, Packet, PacketCodec, Value


def test_datagrams_are_byte_for_byte_the_codecs() -> None:
    codec = PacketCodec()
    token = 0x0123456789ABCDEF
    packets: list[Packet] = [Value(3, 7, 123, 2.5), Batch(4, 9, [1, 2], [1.0, -2.0]),
                             Error(5, "why", 3), Value(1, 0, 0, {"data": [1, 2, 3]})]
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(10.0)

    async def send_all() -> None:
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            asyncio.DatagramProtocol, local_addr=("127.0.0.1", 0))
        try:
            sink = UdpSink(transport, codec, token, rx.getsockname(), 1400)
            for p in packets:
                assert sink.send(p, data=True)
        finally:
            transport.close()

    with rx:
        asyncio.run(send_all())
        got = [rx.recv(65536) for _ in packets]
    assert got == [codec.encode_datagram(p, token) for p in packets]
    assert [codec.decode_datagram(d) for d in got] == [(0, token, p) for p in packets]
