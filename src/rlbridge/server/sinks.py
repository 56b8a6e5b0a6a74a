"""Where a session's outgoing packets go: one small class per transport, one interface.

A channel does not care whether it rides TCP or UDP; it hands packets to a sink. The TCP sink
appends frames to the transport's buffer and refuses (counts) data once a slow client lets
``max_write_buffer`` bytes pile up, so one stalled reader cannot grow the server's memory. The
UDP sink sends one datagram per packet to the client's last seen address, splitting batches that
would exceed the datagram budget.
"""

from __future__ import annotations

import asyncio
from typing import Protocol

from rlbridge.wire import Batch, Packet, PacketCodec


class PacketSink(Protocol):
    """Send a packet; ``data=True`` marks a value packet that may be dropped under pressure."""

    def send(self, packet: Packet, *, data: bool = False) -> bool: ...

    @property
    def dropped(self) -> int: ...


class TcpSink:
    """Frames into one TCP transport."""

    def __init__(self, transport: asyncio.Transport, codec: PacketCodec, max_buffer: int) -> None:
        self._transport = transport
        self._codec = codec
        self._max_buffer = max_buffer
        self._dropped = 0

    @property
    def dropped(self) -> int:
        return self._dropped

    def send(self, packet: Packet, *, data: bool = False) -> bool:
        transport = self._transport
        if transport.is_closing():
            self._dropped += data
            return False
        if data and transport.get_write_buffer_size() > self._max_buffer:
            self._dropped += 1
            return False
        transport.write(self._codec.encode_frame(packet))
        return True


class UdpSink:
    """Datagrams to one client address, tagged with its session token."""

    def __init__(
        self,
        transport: asyncio.DatagramTransport,
        codec: PacketCodec,
        token: int,
        addr: tuple[str, int],
        max_payload: int,
    ) -> None:
        self._transport = transport
        self._codec = codec
        self._token = token
        self.addr = addr
        self._max_payload = max_payload
        self._dropped = 0

    @property
    def dropped(self) -> int:
        return self._dropped

    def send(self, packet: Packet, *, data: bool = False) -> bool:
        if self._transport.is_closing():
            self._dropped += data
            return False
        datagram = self._codec.encode_datagram(packet, self._token)
        if len(datagram) > self._max_payload and isinstance(packet, Batch):
            return self._split(packet)
        if len(datagram) > self._max_payload and data:
            self._dropped += 1  # a single value larger than a datagram: refuse, counted
            return False
        self._transport.sendto(datagram, self.addr)
        return True

    def _split(self, batch: Batch) -> bool:
        n = len(batch.values)
        if n <= 1:
            self._dropped += n
            return False
        half = n // 2
        first = Batch(batch.channel, batch.first_seq, batch.stamps[:half], batch.values[:half])
        rest = Batch(
            batch.channel, batch.first_seq + half, batch.stamps[half:], batch.values[half:]
        )
        ok_first = self.send(first, data=True)
        return self.send(rest, data=True) and ok_first
