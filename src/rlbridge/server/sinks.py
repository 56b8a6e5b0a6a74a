"""Where a session's outgoing packets go: one small class per transport, one interface.

A channel does not care whether it rides TCP or UDP; it hands packets to a sink. The TCP sink
appends frames to the transport's buffer and refuses (counts) data once a slow client lets
``max_write_buffer`` bytes pile up, so one stalled reader cannot grow the server's memory,
and keeps value frames within what a client reads (``CLIENT_MAX_PACKET``: a longer frame ends
its session), cutting a batch and leaving out a value alone over it. A value left out of a
packet that is otherwise sent is told to ``left_out`` (the session's: it counts in the
channel's ``dropped``, what ``rlbridge stats`` shows); a packet not sent at all is counted by
the caller, to which ``send`` returns False. The
UDP sink sends datagrams to the client's last seen address, splitting batches that would exceed
the datagram budget; to a client that reads bundles it sends every channel's values of one loop
iteration together (a ``Bundle`` per datagram budget), to any other one datagram per packet.

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
import logging
from collections.abc import Callable
from typing import Protocol

import msgspec

from rlbridge.tcpstate import congested
from rlbridge.wire import PROTOCOL_VERSION, Batch, Packet, PacketCodec, Value
from rlbridge.wire.bundle import DatagramPacker
from rlbridge.wire.codec import (
    DATAGRAM_HEADER,
    DEFAULT_MAX_PACKET,
    FRAME_HEADER,
    MAGIC,
    MAX_DATAGRAM,
    encode_run_into,
)

log = logging.getLogger("rlbridge.server")

#: The largest frame body a client reads: not announced, so the reference client's (its
#: ``FrameDecoder`` ends the session on a longer one; docs/protocol.md 2).
CLIENT_MAX_PACKET = DEFAULT_MAX_PACKET
_FRAME_HEAD: int = FRAME_HEADER.size
#: A frame (header included) longer than this is over ``CLIENT_MAX_PACKET``.
_FRAME_LIMIT: int = CLIENT_MAX_PACKET + _FRAME_HEAD

#: PacketCodec's encoder settings (msgspec defaults); tests/server check the bytes match.
_ENCODE = msgspec.msgpack.Encoder().encode
#: Values of these types make a ``Value`` of at most 34 bytes, which always fits a datagram
#: (``udp_payload`` is at least 256): the UDP sink may gather them unencoded.
_SCALARS = frozenset((float, int, bool))


def _uncounted(channel: int, count: int) -> None:
    """A sink's ``left_out`` until a session sets its own (a sink without one: tests)."""


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
        #: Told ``(channel, count)`` of the values a sent packet left out (module doc).
        self.left_out: Callable[[int, int], None] = _uncounted
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
        if len(corked) > _FRAME_LIMIT:  # a MiB corked: this frame may be over the limit
            return self._over(packet)
        self._corked_frames += 1
        return True

    def _over(self, packet: Packet) -> bool:
        """The corked frames passed the client's limit: one check per send found it (not a
        frame's own length, which would cost every send). Encoded again alone, the last
        frame is either over the limit (taken back and cut) or fine, and then what is corked
        goes to the transport now, so the next frames start a fresh buffer."""
        corked = self._corked
        size = len(self._codec.encode_frame(packet))
        if size <= _FRAME_LIMIT:
            self._corked_frames += 1
            self.flush()
            return True
        del corked[len(corked) - size:]
        return self._cut(packet)

    def _cut(self, packet: Packet) -> bool:
        """A value frame over the client's limit, which would end its session: a ``Batch`` is
        cut into frames that fit (:func:`~rlbridge.wire.codec.encode_run_into`); a value
        alone over it is not sent. False: nothing was sent (the caller counts it dropped)."""
        refused: list[tuple[int, int]] = []
        frames = 0
        if isinstance(packet, Batch):
            frames = encode_run_into(self._codec, self._corked, packet.channel,
                                     packet.first_seq, packet.stamps, packet.values,
                                     len(packet.values), CLIENT_MAX_PACKET, refused)
            self._corked_frames += frames
            if frames and refused:  # the caller counts only a packet not sent at all
                self._dropped += len(refused)
                self.left_out(packet.channel, len(refused))
        elif isinstance(packet, Value):
            refused.append((packet.seq, len(self._codec.encode_frame(packet)) - _FRAME_HEAD))
        for seq, size in refused:
            log.warning("value %d is %d bytes encoded, over a client's limit of %d bytes; "
                        "not sent", seq, size, CLIENT_MAX_PACKET)
        return frames > 0

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
    """Datagrams to one client address, tagged with its session token.

    Value packets go through a :class:`~rlbridge.wire.bundle.DatagramPacker`. Once the client
    has said it reads bundles (``bundles``, set from its datagrams' flags) they are corked like
    the TCP sink's frames: gathered while the loop handles one burst and sent at the end of the
    iteration (``call_soon``) as bundles of every channel, one datagram and one ``sendto`` per
    ``max_payload`` bytes instead of one per value. Control packets flush what is corked first,
    so order is kept.

    The common corked value (one number: it cannot be too large) is not even encoded when it
    is sent: the iteration's values are kept as they are and encoded as one ``Bundle`` at the
    flush, one msgspec call for all of them (the packer's ``send_parts``, as the SDK's send
    round does), and with keys sealed once; the bytes are those the packer would have made.
    Only if that bundle would not fit one datagram do they go through the packer one by one,
    as any other value does.

    A control packet no datagram can carry is not sent but handed to ``too_large`` (the
    session's: server/datagram_limit.py), which counts it and may give a small answer to send
    in its place.
    """

    def __init__(
        self,
        transport: asyncio.DatagramTransport,
        codec: PacketCodec,
        token: int,
        addr: tuple[str, int],
        max_payload: int,
        loop: asyncio.AbstractEventLoop | None = None,
        too_large: Callable[[Packet, int], Packet | None] | None = None,
    ) -> None:
        self._transport = transport
        self._too_large = too_large
        self._codec = codec
        self._token = token
        self._loop = loop
        #: Without keys every datagram of this sink starts with the same header: packed once,
        #: and the body encoded by msgspec directly (what ``encode_datagram`` produces, one
        #: Python call less per datagram). A sealing codec keeps its own path.
        self._header = (DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, 0, token)
                        if type(codec) is PacketCodec else None)
        self.addr = addr
        self._packer = DatagramPacker(codec, token, max_payload, self._sendto, bundles=False)
        #: A flush is scheduled for the end of this loop iteration.
        self._corked = False
        #: Corked scalar values not yet encoded (they come before anything in the packer).
        self._values: list[Value] = []
        #: Numbers may wait unencoded: values are corked (``bundles`` sets it).
        self._defer = False
        #: A value went to the packer this iteration: later numbers follow it there (order).
        self._packed = False
        self._dropped = 0
        #: Told ``(channel, count)`` of the values a sent packet left out (module doc).
        self.left_out: Callable[[int, int], None] = _uncounted
        self.bytes_out = 0

    @property
    def dropped(self) -> int:
        return self._dropped

    @property
    def bundles(self) -> bool:
        """The client reads bundles: values are corked per loop iteration and bundled."""
        return self._packer.bundles

    @bundles.setter
    def bundles(self, on: bool) -> None:
        self._spill()
        self._packer.flush()
        self._packer.bundles = on
        self._defer = on and self._loop is not None

    @property
    def datagrams(self) -> int:
        """Value datagrams sent (a bundle counts once)."""
        return self._packer.datagrams

    def congested(self) -> bool:
        return False

    def send(self, packet: Packet, *, data: bool = False) -> bool:
        # inlines: PacketCodec.encode_datagram, DatagramPacker.add
        if self._transport.is_closing():
            self._dropped += data
            return False
        if (self._defer and type(packet) is Value and data and not self._packed
                and type(packet.value) in _SCALARS):
            if not self._corked:
                self._cork()
            self._values.append(packet)  # encoded at the flush, with the others
            return True
        packer = self._packer
        if not data or (type(packet) is not Value and not isinstance(packet, Batch)):
            self._spill()
            packer.flush()  # corked values first: the order of sends is the order on the wire
            header = self._header
            datagram = (header + _ENCODE(packet) if header is not None
                        else self._codec.encode_datagram(packet, self._token))
            if len(datagram) > MAX_DATAGRAM:
                return self._refuse(packet, len(datagram))
            self._sendto(datagram)
            return True
        if packer.bundles and self._loop is not None:
            if not self._corked:
                self._cork()
            self._spill()
            self._packed = True
            refused = packer.add(packet)
        else:
            refused = packer.add(packet)
            packer.flush()
        if refused:  # values larger than a datagram: refused, counted
            self._dropped += refused
            if isinstance(packet, Value) or refused == len(packet.values):
                return False  # nothing sent: the caller counts it
            self.left_out(packet.channel, refused)
        return True

    def _refuse(self, packet: Packet, size: int) -> bool:
        """``packet`` would be a datagram of ``size`` bytes, over the limit: its answer, if
        any, goes instead (class doc)."""
        answer = self._too_large(packet, size) if self._too_large is not None else None
        if answer is not None:
            self.send(answer)
        return False

    def _cork(self) -> None:
        """Send what this loop iteration gathers at its end (once per iteration)."""
        assert self._loop is not None
        self._corked = True
        self._loop.call_soon(self.flush)

    def flush(self) -> None:
        """Send the corked values (the end of the loop iteration that gathered them)."""
        self._corked = False
        self._packed = False
        values = self._values
        if self._transport.is_closing():
            self._values = []
            self._dropped += len(values) + self._packer.discard()
            return
        if values and self._packer.send_parts(values):  # one encode for all, if one datagram
            self._values = []
            return
        self._spill()
        self._packer.flush()

    def _spill(self) -> None:
        """Hand the values waiting unencoded to the packer (before anything sent after them)."""
        values = self._values
        if values:
            self._values = []
            add = self._packer.add
            for value in values:
                add(value)  # a scalar value always fits: nothing is refused

    def _sendto(self, datagram: bytes) -> None:
        self.bytes_out += len(datagram)
        self._transport.sendto(datagram, self.addr)
