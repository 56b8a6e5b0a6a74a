"""Where a session's outgoing packets go: one small class per transport, one interface.

A channel does not care whether it rides TCP or UDP; it hands packets to a sink. The TCP sink
appends frames to the transport's buffer and refuses (counts) data once a slow client lets
``max_write_buffer`` bytes pile up, so one stalled reader cannot grow the server's memory. The
UDP sink sends one datagram per packet to the client's last seen address, splitting batches that
would exceed the datagram budget.

The TCP sink corks value frames: those written while the loop handles one burst of input are
gathered in one buffer and handed to the transport once, at the end of the loop iteration
(``call_soon``), so a burst of a hundred one-value packets costs one ``send`` system call, not a
hundred. Control frames (acks, errors, heartbeats, goodbyes) flush what is corked and go out at
once, so the order on the stream is the order of ``send`` calls and a close never loses them.

``congested()`` tells latest-value channels (docs/policies.md) whether a value written now
would queue: on TCP, bytes waiting in the transport's buffer or in the kernel's send queue
(:mod:`rlbridge.tcpstate`); a UDP sink never queues.
"""

from __future__ import annotations

import asyncio
from typing import Protocol

import msgspec

from rlbridge.tcpstate import congested
from rlbridge.wire import PROTOCOL_VERSION, Batch, Packet, PacketCodec
from rlbridge.wire.codec import DATAGRAM_HEADER, MAGIC

#: PacketCodec's encoder settings (msgspec defaults); tests/server check the bytes match.
_ENCODE = msgspec.msgpack.Encoder().encode


class PacketSink(Protocol):
    """Send a packet; ``data=True`` marks a value packet that may be dropped under pressure."""

    def send(self, packet: Packet, *, data: bool = False) -> bool: ...

    @property
    def dropped(self) -> int: ...

    def congested(self) -> bool: ...


class TcpSink:
    """Frames into one TCP transport; value frames corked per loop iteration (module doc)."""

    def __init__(self, transport: asyncio.Transport, codec: PacketCodec, max_buffer: int,
                 loop: asyncio.AbstractEventLoop | None = None) -> None:
        self._transport = transport
        self._codec = codec
        self._max_buffer = max_buffer
        self._loop = loop
        self._corked = bytearray()
        self._corked_frames = 0
        self._dropped = 0
        self._sock = transport.get_extra_info("socket")
        self.bytes_out = 0

    @property
    def dropped(self) -> int:
        return self._dropped

    def congested(self) -> bool:
        """A value written now would wait: in our buffer, or in the kernel's (module doc)."""
        transport = self._transport
        if transport.is_closing() or transport.get_write_buffer_size() > 0:
            return True
        return self._sock is not None and congested(self._sock)

    def send(self, packet: Packet, *, data: bool = False) -> bool:
        transport = self._transport
        if transport.is_closing():
            self._dropped += data
            return False
        corked = self._corked
        if data and transport.get_write_buffer_size() + len(corked) > self._max_buffer:
            self._dropped += 1
            return False
        if not data or self._loop is None:
            self.flush()
            frame = self._codec.encode_frame(packet)
            self.bytes_out += len(frame)
            transport.write(frame)
            return True
        if not corked:
            self._loop.call_soon(self.flush)
        self._codec.encode_frame_into(packet, corked)
        self._corked_frames += 1
        return True

    @property
    def queued(self) -> int:
        """Bytes waiting for this client: the transport's buffer and the corked frames."""
        return self._transport.get_write_buffer_size() + len(self._corked)

    def flush(self) -> None:
        """Hand the corked frames to the transport (which owns the buffer from then on)."""
        corked = self._corked
        if corked:
            self._corked = bytearray()
            frames, self._corked_frames = self._corked_frames, 0
            if self._transport.is_closing():
                self._dropped += frames
            else:
                self.bytes_out += len(corked)
                self._transport.write(corked)


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
        #: Without keys every datagram of this sink starts with the same header: packed once,
        #: and the body encoded by msgspec directly (what ``encode_datagram`` produces, one
        #: Python call less per datagram). A sealing codec keeps its own path.
        self._header = (DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, token)
                        if type(codec) is PacketCodec else None)
        self.addr = addr
        self._max_payload = max_payload
        self._dropped = 0
        self.bytes_out = 0

    @property
    def dropped(self) -> int:
        return self._dropped

    def congested(self) -> bool:
        return False

    def send(self, packet: Packet, *, data: bool = False) -> bool:
        if self._transport.is_closing():
            self._dropped += data
            return False
        header = self._header
        if header is not None:
            datagram = header + _ENCODE(packet)
        else:
            datagram = self._codec.encode_datagram(packet, self._token)
        if len(datagram) > self._max_payload and isinstance(packet, Batch):
            return self._split(packet, len(datagram))
        if len(datagram) > self._max_payload and data:
            self._dropped += 1  # a single value larger than a datagram: refuse, counted
            return False
        self.bytes_out += len(datagram)
        self._transport.sendto(datagram, self.addr)
        return True

    def _split(self, batch: Batch, size: int) -> bool:
        """Send ``batch`` (encoded: ``size`` bytes) as consecutive batches that fit.

        The chunk length is estimated from the encoded size once, instead of halving and
        re-encoding the whole batch at every level; a chunk that still does not fit (values of
        very different sizes) is split again the same way.
        """
        n = len(batch.values)
        if n <= 1:
            self._dropped += n
            return False
        per = max(1, min(n // 2, n * (self._max_payload - 64) // size))
        ok = True
        for i in range(0, n, per):
            part = Batch(batch.channel, batch.first_seq + i, batch.stamps[i : i + per],
                         batch.values[i : i + per])
            ok = self.send(part, data=True) and ok
        return ok
