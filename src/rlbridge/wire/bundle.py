"""Value packets into datagrams: several channels per datagram when the peer reads bundles.

Theory of operation. A sender hands the packer every value packet of one send round (the
client's send thread: every UDP channel's pending values; the server: every value one event-loop
iteration produced for one session), then calls :meth:`DatagramPacker.flush`. The packer keeps
the encoded parts until the next one would push the datagram past ``budget`` bytes, and then
hands the finished datagram to ``send``: one datagram, one system call and one wake-up of the
receiver for all the channels of a round (docs/protocol.md 6.16), where one per channel was
sent before.

A round with a single part goes out as that plain ``Value`` or ``Batch``, byte for byte what a
sender without bundles writes; only two or more parts make a ``Bundle``. A peer that has not
said it reads bundles (``bundles=False``) gets one datagram per part, as before.

The bundle body is assembled from the parts' encodings (the prefix ``92 20``: a two-element
array and tag 32, then the parts' array header), so each part is encoded exactly once; the bytes
are the same as encoding a ``Bundle`` packet. Without keys the datagram is the header and that
body; a sealing codec seals the same body (``seal_body``), so sealing adds the AEAD and nothing
else: no second encoding.

A sender that has a whole round at hand (the client's send thread) may instead give every
part at once to :meth:`DatagramPacker.send_parts`, as packets or as plain tuples shaped like
them (``(VALUE_TAG, channel, seq, stamp_ns, value)``: an array-like tagged struct is encoded
as exactly that array). With a plain codec and bundles on, the round is then encoded by one
msgspec call into a reused buffer behind the datagram header: no ``Value`` object, no
per-part encoding and no join per value. A round that does not fit ``budget`` is left to the
caller, who adds its parts one by one (:func:`as_packet`).

A part larger than ``budget`` on its own is split when it is a batch (into consecutive batches
that fit, the chunk length estimated once from the encoded size); a single value goes alone if
it fits ``limit`` and is refused (counted by the caller) if not.

Sans-IO: no sockets, no clocks; ``send`` is the caller's.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from typing import Any

import msgspec

from rlbridge.wire.codec import DATAGRAM_HEADER, MAGIC, PacketCodec
from rlbridge.wire.packets import PROTOCOL_VERSION, Batch, Bundle, Value
from rlbridge.wire.seal import SEAL_OVERHEAD, SealedCodec

#: ``[32, parts]``: fixarray of 2, tag 32, then the parts' array: ``dc`` + u16 count (array16),
#: or a fixarray ``0x90 | n`` when there are at most 15 parts.
BUNDLE_PREFIX = b"\x92\x20\xdc"
_COUNT = struct.Struct(">H")
_FIXARRAYS = [b"\x92\x20" + bytes([0x90 | n]) for n in range(16)]
#: Bytes a bundle adds to its parts, at most: the prefix and the u16 count.
BUNDLE_OVERHEAD = len(BUNDLE_PREFIX) + _COUNT.size
#: At most this many parts in one bundle (the array16 count).
MAX_PARTS = 0xFFFF

ValuePacket = Value | Batch
#: The wire tags of ``Value``, ``Batch`` and ``Bundle`` (the first element of their arrays).
VALUE_TAG: int = Value.__struct_config__.tag  # type: ignore[assignment]
BATCH_TAG: int = Batch.__struct_config__.tag  # type: ignore[assignment]
BUNDLE_TAG: int = Bundle.__struct_config__.tag  # type: ignore[assignment]
#: A part of a round: a packet, or a tuple with its tag and fields (encodes to the same bytes).
Part = ValuePacket | tuple[Any, ...]


def as_packet(part: Part) -> ValuePacket:
    """The packet a part stands for (a tuple becomes its ``Value`` or ``Batch``)."""
    if not isinstance(part, tuple):
        return part
    if part[0] == VALUE_TAG:
        return Value(*part[1:])
    if part[0] == BATCH_TAG:
        return Batch(*part[1:])
    raise ValueError(f"not a value part: tag {part[0]!r}")


class DatagramPacker:
    """Gathers value packets and hands ``send`` datagrams of at most ``budget`` bytes.

    ``limit`` is the largest datagram a single value may make when it does not fit ``budget``
    (the client: the IPv4 maximum; the server: its payload limit, so an oversized value is
    refused). ``bundles`` may be switched on later (the server learns it from the peer).
    """

    def __init__(self, codec: PacketCodec, token: int, budget: int,
                 send: Callable[[bytes], object], *, limit: int | None = None,
                 bundles: bool = True, flags: int = 0) -> None:
        self.codec = codec
        self.token = token
        self._flags = flags
        self._send = send
        self.budget = budget
        self.limit = budget if limit is None else limit
        self.bundles = bundles
        self._plain = type(codec) is PacketCodec
        #: A sealing codec's ``seal_body`` (the datagram around an encoded body), else None.
        self._seal = codec.seal_body if isinstance(codec, SealedCodec) else None
        self._header = DATAGRAM_HEADER.pack(MAGIC, PROTOCOL_VERSION, flags, token)
        # A sealing codec adds exactly SEAL_OVERHEAD (counter and tag) to the body, so a sealed
        # datagram holds as many values as the budget allows: a margin beyond it would only
        # make more, smaller datagrams, each paying the cipher call and its system calls.
        self._overhead = DATAGRAM_HEADER.size + (0 if self._plain else SEAL_OVERHEAD)
        encoder = msgspec.msgpack.Encoder()
        self._encode = encoder.encode
        self._encode_into = encoder.encode_into
        self._round = bytearray(self._header)
        self._bundle: list[Any] = [BUNDLE_TAG, None]
        self._bodies: list[bytes] = []
        self._size = 0
        self._values = 0
        #: Datagrams handed to ``send``, and of those, bundles (two or more parts).
        self.datagrams = 0
        self.bundles_sent = 0

    @property
    def one_call(self) -> bool:
        """:meth:`send_parts` can encode a round in one call (a codec that bundles; a sealing
        codec then seals that one encoding)."""
        return self.bundles

    @property
    def sealed(self) -> bool:
        """Its datagrams are sealed (a session with keys)."""
        return self._seal is not None

    @property
    def pending(self) -> int:
        """Parts waiting for :meth:`flush`."""
        return len(self._bodies)

    def add(self, packet: ValuePacket) -> int:
        """Take one value packet; return how many of its values were refused as too large."""
        body = self._encode(packet)
        size = len(body)
        if self._overhead + size > self.budget:
            return self._oversized(packet, body)
        if not self.bundles:
            self._emit(body)
            return 0
        bodies = self._bodies
        if bodies and (self._overhead + BUNDLE_OVERHEAD + self._size + size > self.budget
                       or len(bodies) >= MAX_PARTS):
            self.flush()
            bodies = self._bodies  # a new list: flush handed the old one on
        bodies.append(body)
        self._size += size
        self._values += 1 if isinstance(packet, Value) else len(packet.values)
        return 0

    def send_parts(self, parts: Sequence[Part],
                   send: Callable[[bytes], object] | None = None) -> bool:
        """Send a whole round's parts in one datagram, encoded by one msgspec call.

        Returns False, having sent nothing, when this packer cannot (not :attr:`one_call`) or
        :meth:`add` would not put the parts in one datagram: the caller then adds them one by
        one. So the datagrams are the same either way; one call only encodes them faster. (The
        SDK's send round and the server's UDP sink both send their rounds through here.)
        ``send`` replaces the packer's own for this datagram (a sender that must not wait);
        what it raises leaves ``parts`` as they were and counts no datagram.
        """
        # inlines: DatagramPacker.add, DatagramPacker.flush
        n = len(parts)
        if not (n and self.bundles):
            return False
        if self._seal is not None:
            return self._seal_parts(parts, send)
        buf = self._round
        if n == 1:
            self._encode_into(parts[0], buf, DATAGRAM_HEADER.size)
            size = len(buf)
        else:
            bundle = self._bundle
            bundle[1] = parts  # [32, parts]: the Bundle's array, its parts unchanged
            self._encode_into(bundle, buf, DATAGRAM_HEADER.size)
            # add() reserves BUNDLE_OVERHEAD for the array header, which a fixarray (up to
            # 15 parts) makes two bytes shorter: the same reserve here, the same datagrams.
            size = len(buf) + (2 if n < 16 else 0)
        if size > self.budget or n > MAX_PARTS:
            return False
        if self._bodies:  # parts added before this round go first
            self.flush()
        (self._send if send is None else send)(bytes(buf))
        self.datagrams += 1
        self.bundles_sent += n > 1
        return True

    def _seal_parts(self, parts: Sequence[Part],
                    send: Callable[[bytes], object] | None) -> bool:
        """:meth:`send_parts` of a sealing codec: the round's body in one call, then sealed
        (the same size test, so the same datagrams as :meth:`add` makes)."""
        n = len(parts)
        if n == 1:
            body = self._encode(parts[0])
            reserve = 0
        else:
            bundle = self._bundle
            bundle[1] = parts
            body = self._encode(bundle)
            reserve = 2 if n < 16 else 0  # add()'s reserve for the array header, as above
        if self._overhead + len(body) + reserve > self.budget or n > MAX_PARTS:
            return False
        if self._bodies:
            self.flush()
        assert self._seal is not None
        (self._send if send is None else send)(self._seal(body, self.token, self._flags))
        self.datagrams += 1
        self.bundles_sent += n > 1
        return True

    def flush(self) -> None:
        """Send what is gathered: one part as itself, several as one bundle.

        What was gathered is forgotten even if ``send`` raises: a failed datagram is not sent
        again with the next round's.
        """
        bodies = self._bodies
        if not bodies:
            return
        self.discard()
        n = len(bodies)
        if n == 1:
            self._emit(bodies[0])
            return
        self.bundles_sent += 1
        self.datagrams += 1
        # The smallest array header, as msgspec writes it (the same bytes as encoding a
        # Bundle): a fixarray up to 15 parts, else an array16.
        count = _FIXARRAYS[n] if n < 16 else BUNDLE_PREFIX + _COUNT.pack(n)
        if self._seal is None:
            self._send(b"".join((self._header, count, *bodies)))
        else:
            self._send(self._seal(b"".join((count, *bodies)), self.token, self._flags))

    def discard(self) -> int:
        """Forget what is gathered (the peer is gone); return how many values that was."""
        values = self._values
        self._bodies = []
        self._size = 0
        self._values = 0
        return values

    def _emit(self, body: bytes) -> None:
        """One encoded packet alone in a datagram."""
        self.datagrams += 1
        if self._seal is None:
            self._send(self._header + body)
        else:
            self._send(self._seal(body, self.token, self._flags))

    def _oversized(self, packet: ValuePacket, body: bytes) -> int:
        """A part that does not fit ``budget`` alone: split a batch, send or refuse a value."""
        n = len(packet.values) if isinstance(packet, Batch) else 1
        if n > 1:
            assert isinstance(packet, Batch)
            # From the room for the body alone (64 bytes spare for what varies per chunk), so
            # a sealed packer with SEAL_OVERHEAD more budget splits exactly as a plain one.
            room = self.budget - self._overhead - 64
            per = max(1, min(n // 2, n * room // len(body)))
            refused = 0
            for i in range(0, n, per):
                refused += self.add(Batch(packet.channel, packet.first_seq + i,
                                          packet.stamps[i : i + per],
                                          packet.values[i : i + per]))
            return refused
        if self._overhead + len(body) > self.limit:
            return n
        self.flush()  # keep the order of parts
        self._emit(body)
        return 0
