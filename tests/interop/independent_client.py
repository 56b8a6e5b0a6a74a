"""A from-scratch rlbridge client written only from ``docs/protocol.md``.

It checks the document, not the Python SDK: nothing here imports ``rlbridge`` or ``msgspec``.
The standard library (``socket``, ``struct``, ``select``) and the hand-written MessagePack
subset of the protocol document's primer (section 5) are all it uses, so a disagreement
between this client and the server is a disagreement between the document and the server.

Layout, following the document:

* MessagePack subset (doc section 5): :func:`packb`, :func:`unpackb`.
* Framing (doc sections 2, 3): :func:`frame`, :class:`FrameReader`, :func:`datagram`,
  :func:`parse_datagram`.
* Packet bodies (doc sections 4, 6): ``TAG_*`` constants and small constructors returning the
  MessagePack array of each packet.
* Sequence rule (doc section 10.2): :class:`SequenceFilter`.
* :class:`IndependentClient`: sockets, handshake (doc section 8), answering heartbeats with an
  echo (doc section 11), topic binding (doc section 9), values, stats, goodbye.
* :func:`run_scenario`: the whole walk-through against a server; ``python
  independent_client.py HOST PORT`` runs it from a shell.
"""

from __future__ import annotations

import contextlib
import math
import select
import socket
import struct
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

# -- MessagePack subset (doc section 5) ------------------------------------------------------


class MsgPackError(ValueError):
    """Bytes that are not the MessagePack subset of the protocol document."""


def packb(obj: Any) -> bytes:
    """Encode ``obj`` (None, bool, int, float, str, bytes, list/tuple, dict) as MessagePack."""
    out = bytearray()
    _pack(obj, out)
    return bytes(out)


def _pack(obj: Any, out: bytearray) -> None:
    if obj is None:
        out.append(0xC0)
    elif obj is True:
        out.append(0xC3)
    elif obj is False:
        out.append(0xC2)
    elif isinstance(obj, int):
        _pack_int(obj, out)
    elif isinstance(obj, float):
        out.append(0xCB)
        out += struct.pack(">d", obj)
    elif isinstance(obj, str):
        raw = obj.encode("utf-8")
        n = len(raw)
        if n <= 31:
            out.append(0xA0 | n)
        elif n <= 0xFF:
            out += bytes((0xD9, n))
        elif n <= 0xFFFF:
            out += b"\xda" + struct.pack(">H", n)
        else:
            out += b"\xdb" + struct.pack(">I", n)
        out += raw
    elif isinstance(obj, bytes | bytearray):
        n = len(obj)
        if n <= 0xFF:
            out += bytes((0xC4, n))
        elif n <= 0xFFFF:
            out += b"\xc5" + struct.pack(">H", n)
        else:
            out += b"\xc6" + struct.pack(">I", n)
        out += obj
    elif isinstance(obj, list | tuple):
        n = len(obj)
        if n <= 15:
            out.append(0x90 | n)
        elif n <= 0xFFFF:
            out += b"\xdc" + struct.pack(">H", n)
        else:
            out += b"\xdd" + struct.pack(">I", n)
        for item in obj:
            _pack(item, out)
    elif isinstance(obj, dict):
        n = len(obj)
        if n <= 15:
            out.append(0x80 | n)
        elif n <= 0xFFFF:
            out += b"\xde" + struct.pack(">H", n)
        else:
            out += b"\xdf" + struct.pack(">I", n)
        for key, value in obj.items():
            _pack(key, out)
            _pack(value, out)
    else:
        raise TypeError(f"cannot encode {type(obj).__name__} in the protocol's MessagePack subset")


def _pack_int(n: int, out: bytearray) -> None:
    if 0 <= n <= 0x7F:
        out.append(n)
    elif -32 <= n < 0:
        out.append(n & 0xFF)
    elif 0 <= n <= 0xFF:
        out += bytes((0xCC, n))
    elif 0 <= n <= 0xFFFF:
        out += b"\xcd" + struct.pack(">H", n)
    elif 0 <= n <= 0xFFFF_FFFF:
        out += b"\xce" + struct.pack(">I", n)
    elif 0 <= n <= 0xFFFF_FFFF_FFFF_FFFF:
        out += b"\xcf" + struct.pack(">Q", n)
    elif n >= -0x80:
        out += b"\xd0" + struct.pack(">b", n)
    elif n >= -0x8000:
        out += b"\xd1" + struct.pack(">h", n)
    elif n >= -0x8000_0000:
        out += b"\xd2" + struct.pack(">i", n)
    elif n >= -0x8000_0000_0000_0000:
        out += b"\xd3" + struct.pack(">q", n)
    else:
        raise OverflowError(f"{n} does not fit a MessagePack integer")


# Fixed-size scalars: type byte -> struct format.
_FIXED = {
    0xCA: ">f", 0xCB: ">d",
    0xCC: ">B", 0xCD: ">H", 0xCE: ">I", 0xCF: ">Q",
    0xD0: ">b", 0xD1: ">h", 0xD2: ">i", 0xD3: ">q",
}
# Variable-size: type byte -> (kind, struct format of the length).
_SIZED = {
    0xD9: ("str", ">B"), 0xDA: ("str", ">H"), 0xDB: ("str", ">I"),
    0xC4: ("bin", ">B"), 0xC5: ("bin", ">H"), 0xC6: ("bin", ">I"),
    0xDC: ("array", ">H"), 0xDD: ("array", ">I"),
    0xDE: ("map", ">H"), 0xDF: ("map", ">I"),
}


def unpackb(data: bytes | memoryview) -> Any:
    """Decode exactly one MessagePack value that spans all of ``data``."""
    view = memoryview(data)
    value, pos = _unpack(view, 0)
    if pos != len(view):
        raise MsgPackError(f"{len(view) - pos} bytes after the value")
    return value


def _take(view: memoryview, pos: int, n: int) -> memoryview:
    if pos + n > len(view):
        raise MsgPackError("truncated MessagePack value")
    return view[pos : pos + n]


def _unpack(view: memoryview, pos: int) -> tuple[Any, int]:
    b = _take(view, pos, 1)[0]
    pos += 1
    if b <= 0x7F:
        return b, pos
    if b >= 0xE0:
        return b - 0x100, pos
    if 0xA0 <= b <= 0xBF:
        return _str(view, pos, b & 0x1F)
    if 0x90 <= b <= 0x9F:
        return _array(view, pos, b & 0x0F)
    if 0x80 <= b <= 0x8F:
        return _map(view, pos, b & 0x0F)
    if b == 0xC0:
        return None, pos
    if b == 0xC2:
        return False, pos
    if b == 0xC3:
        return True, pos
    if b in _FIXED:
        fmt = _FIXED[b]
        size = struct.calcsize(fmt)
        return struct.unpack(fmt, _take(view, pos, size))[0], pos + size
    if b in _SIZED:
        kind, fmt = _SIZED[b]
        size = struct.calcsize(fmt)
        n = struct.unpack(fmt, _take(view, pos, size))[0]
        pos += size
        if kind == "str":
            return _str(view, pos, n)
        if kind == "bin":
            return bytes(_take(view, pos, n)), pos + n
        if kind == "array":
            return _array(view, pos, n)
        return _map(view, pos, n)
    raise MsgPackError(f"type byte 0x{b:02x} is outside the protocol's MessagePack subset")


def _str(view: memoryview, pos: int, n: int) -> tuple[str, int]:
    try:
        return bytes(_take(view, pos, n)).decode("utf-8"), pos + n
    except UnicodeDecodeError as exc:
        raise MsgPackError(f"string is not UTF-8: {exc}") from None


def _array(view: memoryview, pos: int, n: int) -> tuple[list[Any], int]:
    items = []
    for _ in range(n):
        item, pos = _unpack(view, pos)
        items.append(item)
    return items, pos


def _map(view: memoryview, pos: int, n: int) -> tuple[dict[Any, Any], int]:
    result = {}
    for _ in range(n):
        key, pos = _unpack(view, pos)
        value, pos = _unpack(view, pos)
        result[key] = value
    return result, pos


# -- Framing (doc sections 2 and 3) ----------------------------------------------------------

MAGIC = b"RB"
VERSION = 1
FRAME_HEADER = struct.Struct(">2sBBI")
DATAGRAM_HEADER = struct.Struct(">2sBBQ")
DEFAULT_MAX_PACKET = 1 << 20
UDP_BUDGET = 1400


class ProtocolViolation(Exception):
    """The server sent bytes the document does not allow."""


def frame(body: Sequence[Any], *, version: int = VERSION, magic: bytes = MAGIC) -> bytes:
    """One TCP frame: 8-byte header and the MessagePack body."""
    raw = packb(body)
    return FRAME_HEADER.pack(magic, version, 0, len(raw)) + raw


#: Doc 3: datagram flag bit 7, "this sender reads Bundle packets".
FLAG_BUNDLES = 0x80


def datagram(body: Sequence[Any], token: int, flags: int = 0) -> bytes:
    """One UDP datagram: 12-byte header with the token and the MessagePack body."""
    return DATAGRAM_HEADER.pack(MAGIC, VERSION, flags, token) + packb(body)


def parse_datagram(data: bytes) -> tuple[int, int, Any]:
    """``(flags, token, body)`` of one datagram."""
    if len(data) < DATAGRAM_HEADER.size:
        raise ProtocolViolation(f"datagram of {len(data)} bytes is shorter than its header")
    magic, version, flags, token = DATAGRAM_HEADER.unpack_from(data)
    if magic != MAGIC or version != VERSION:
        raise ProtocolViolation(f"datagram header {magic!r} v{version} is not rlbridge v1")
    return flags, token, unpackb(memoryview(data)[DATAGRAM_HEADER.size :])


class FrameReader:
    """Cuts a TCP byte stream into frame bodies, whatever the read boundaries."""

    def __init__(self, max_packet: int = DEFAULT_MAX_PACKET) -> None:
        self._buf = bytearray()
        self._max = max_packet

    def feed(self, data: bytes) -> list[Any]:
        self._buf += data
        bodies = []
        while len(self._buf) >= FRAME_HEADER.size:
            magic, version, _flags, length = FRAME_HEADER.unpack_from(self._buf)
            if magic != MAGIC or version != VERSION:
                raise ProtocolViolation(f"frame header {magic!r} v{version} is not rlbridge v1")
            if length > self._max:
                raise ProtocolViolation(f"frame of {length} bytes exceeds {self._max}")
            end = FRAME_HEADER.size + length
            if len(self._buf) < end:
                break
            bodies.append(unpackb(memoryview(self._buf)[FRAME_HEADER.size : end]))
            del self._buf[:end]
        return bodies


# -- Packets (doc sections 4 and 6) ----------------------------------------------------------

TAG_HELLO = 1
TAG_CONNECT_ACK = 2
TAG_CONNECT_ERROR = 3
TAG_TOPIC_CONNECT = 4
TAG_TOPIC_ACK = 5
TAG_TOPIC_ERROR = 6
TAG_TOPIC_CLOSE = 7
TAG_VALUE = 8
TAG_BATCH = 9
TAG_HEARTBEAT = 10
TAG_DISCONNECT = 11
TAG_ERROR = 12
TAG_STATS = 13
TAG_AUTH_CHALLENGE = 14
TAG_AUTH_PROOF = 15
TAG_SERVICE_CALL = 20
TAG_SERVICE_RESULT = 21
TAG_SERVICE_OFFER = 22
TAG_SERVICE_REQUEST = 23
TAG_SERVICE_REPLY = 24
TAG_GOAL_SEND = 25
TAG_GOAL_CANCEL = 26
TAG_GOAL_RESULT = 27
TAG_ROS_LOSS = 28
TAG_BUNDLE = 32
TAG_CREDIT = 34
TAG_LOSS_REPORT = 35

TAG_NAMES = {
    TAG_HELLO: "Hello", TAG_CONNECT_ACK: "ConnectAck", TAG_CONNECT_ERROR: "ConnectError",
    TAG_TOPIC_CONNECT: "TopicConnect", TAG_TOPIC_ACK: "TopicAck", TAG_TOPIC_ERROR: "TopicError",
    TAG_TOPIC_CLOSE: "TopicClose", TAG_VALUE: "Value", TAG_BATCH: "Batch",
    TAG_HEARTBEAT: "Heartbeat", TAG_DISCONNECT: "Disconnect", TAG_ERROR: "Error",
    TAG_STATS: "Stats", TAG_AUTH_CHALLENGE: "AuthChallenge", TAG_AUTH_PROOF: "AuthProof",
    TAG_SERVICE_CALL: "ServiceCall", TAG_SERVICE_RESULT: "ServiceResult",
    TAG_SERVICE_OFFER: "ServiceOffer", TAG_SERVICE_REQUEST: "ServiceRequest",
    TAG_SERVICE_REPLY: "ServiceReply", TAG_GOAL_SEND: "GoalSend",
    TAG_GOAL_CANCEL: "GoalCancel", TAG_GOAL_RESULT: "GoalResult",
    TAG_ROS_LOSS: "RosLoss",
    TAG_BUNDLE: "Bundle",
    TAG_CREDIT: "Credit", TAG_LOSS_REPORT: "LossReport",
}

# Error codes (doc section 12.2).
UNSUPPORTED_VERSION = 1
MALFORMED = 2
TOO_LARGE = 3
UNEXPECTED = 4
UNKNOWN_TYPE = 10
TYPE_CLASH = 11
NO_SUCH_FIELD = 12
BAD_VALUE = 13
UNKNOWN_CHANNEL = 14
CHANNEL_IN_USE = 15
BAD_TOPIC = 16
PACKAGE_MISSING = 17
LIMIT = 20
AUTH_FAILED = 21
NOT_ALLOWED = 22
TRANSPORT_DISABLED = 23
SHUTTING_DOWN = 30
INTERNAL = 31


def hello(name: str, protocol: int = VERSION) -> list[Any]:
    return [TAG_HELLO, protocol, name]


def topic_connect(
    channel: int,
    direction: str,
    topic: str,
    msg_type: str,
    field: str | None = "data",
    transport: str = "tcp",
    *,
    redundancy: int = 0,
) -> list[Any]:
    """The shortest array that says what the caller chose (trailing defaults omitted)."""
    body: list[Any] = [TAG_TOPIC_CONNECT, channel, direction, topic, msg_type, field, transport]
    if redundancy:
        # fields 7..10 must be given to reach field 11 (doc section 4).
        body += [1, None, 10, 0, redundancy]
    return body


def value(channel: int, seq: int, stamp_ns: int, val: Any) -> list[Any]:
    return [TAG_VALUE, channel, seq, stamp_ns, val]


def batch(channel: int, first_seq: int, stamps: Sequence[int], values: Sequence[Any]) -> list[Any]:
    return [TAG_BATCH, channel, first_seq, list(stamps), list(values)]


def bundle(*parts: Sequence[Any]) -> list[Any]:
    """Doc 6.16: several Value/Batch bodies in one packet."""
    return [TAG_BUNDLE, [list(p) for p in parts]]


def heartbeat(sent_ns: int, echo_ns: int = 0) -> list[Any]:
    return [TAG_HEARTBEAT, sent_ns, echo_ns]


@dataclass(frozen=True)
class Packet:
    """One decoded packet: its tag, its fields after the tag, and the transport it came on."""

    tag: int
    fields: tuple[Any, ...]
    via: str

    @property
    def name(self) -> str:
        return TAG_NAMES.get(self.tag, f"tag {self.tag}")

    def field(self, index: int, default: Any = None) -> Any:
        """Field ``index`` (1-based, as in the document's tables), or its default if omitted."""
        return self.fields[index - 1] if len(self.fields) >= index else default


def to_packet(body: Any, via: str) -> Packet:
    if not isinstance(body, list) or not body or not isinstance(body[0], int):
        raise ProtocolViolation(f"packet body is not an array starting with a tag: {body!r}")
    return Packet(body[0], tuple(body[1:]), via)


@dataclass(frozen=True)
class ConnectAck:
    session: int
    token: int
    heartbeat_ms: int
    timeout_ms: int
    max_packet: int
    max_channels: int
    max_batch: int

    @classmethod
    def from_packet(cls, p: Packet) -> ConnectAck:
        limits = p.field(5)
        return cls(p.field(1), p.field(2), p.field(3), p.field(4), *limits[:3])


class Refused(Exception):
    """The server answered with an error packet (ConnectError, TopicError or Error)."""

    def __init__(self, packet: Packet) -> None:
        self.packet = packet
        if packet.tag == TAG_TOPIC_ERROR:
            self.channel, self.code, self.reason = packet.fields[:3]
        elif packet.tag == TAG_ERROR:
            self.code, self.reason = packet.fields[:2]
            self.channel = packet.field(3)
        else:
            self.code, self.reason = packet.fields[:2]
            self.channel = None
        super().__init__(f"{packet.name} {self.code}: {self.reason}")


# -- Sequence rule (doc section 10.2) --------------------------------------------------------


class SequenceFilter:
    """Deliver only values newer than the newest delivered; count lost and dropped."""

    def __init__(self) -> None:
        self.highest: int | None = None
        self.lost = 0
        self.duplicates = 0

    def accept(self, first_seq: int, values: Sequence[Any]) -> list[Any]:
        fresh = []
        for i, val in enumerate(values):
            seq = first_seq + i
            if self.highest is None or seq > self.highest:
                if self.highest is not None:
                    self.lost += seq - self.highest - 1
                self.highest = seq
                fresh.append(val)
            else:
                self.duplicates += 1
        return fresh


# -- The client ------------------------------------------------------------------------------


class ClosedByServer(Exception):
    """The server closed the TCP connection."""


@dataclass
class Received:
    """Values of one subscribe channel, after the sequence rule."""

    values: list[Any] = field(default_factory=list)
    stamps: list[int] = field(default_factory=list)
    packets: list[Packet] = field(default_factory=list)
    filter: SequenceFilter = field(default_factory=SequenceFilter)


class IndependentClient:
    """A minimal session: one TCP socket and/or one UDP socket, driven by the caller's thread.

    There is no background thread. Every ``recv*`` call reads both sockets until its
    condition holds or its deadline passes; while reading it answers each server heartbeat
    with a heartbeat echoing the server's stamp (doc section 11), which also keeps the server's
    watchdog fed. Packets nobody has asked for yet wait in ``backlog``.
    """

    def __init__(self, host: str, port: int, *, timeout: float = 3.0,
                 answer_heartbeats: bool = True) -> None:
        self.host, self.port = host, port
        self.timeout = timeout
        self.answer_heartbeats = answer_heartbeats
        self.tcp: socket.socket | None = None
        self.udp: socket.socket | None = None
        self.ack: ConnectAck | None = None
        self.backlog: list[Packet] = []
        self.received: dict[int, Received] = {}
        self.next_seq: dict[int, int] = {}
        self.rtt_samples_ns: list[int] = []
        self.heartbeats_received = {"tcp": 0, "udp": 0}
        self.tcp_eof = False
        self._reader = FrameReader()
        #: Flags of our datagrams (``FLAG_BUNDLES``: the server may send us bundles).
        self.udp_flags = 0
        #: The tag of every datagram received, in order (bundles counted once).
        self.udp_tags: list[int] = []

    # -- sockets ---------------------------------------------------------------------------
    def __enter__(self) -> IndependentClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for sock in (self.tcp, self.udp):
            if sock is not None:
                sock.close()
        self.tcp = self.udp = None

    def open_tcp(self) -> socket.socket:
        self.tcp = socket.create_connection((self.host, self.port), timeout=self.timeout)
        self.tcp.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return self.tcp

    def open_udp(self) -> socket.socket:
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.connect((self.host, self.port))
        return self.udp

    @property
    def token(self) -> int:
        assert self.ack is not None, "no session"
        return self.ack.token

    def send_raw_tcp(self, data: bytes) -> None:
        assert self.tcp is not None, "no TCP connection"
        self.tcp.sendall(data)

    def send_tcp(self, body: Sequence[Any]) -> None:
        self.send_raw_tcp(frame(body))

    def send_udp(self, body: Sequence[Any], token: int | None = None) -> None:
        assert self.udp is not None, "no UDP socket"
        # An ICMP "port unreachable" for an earlier datagram: UDP is lossy anyway.
        with contextlib.suppress(ConnectionRefusedError):
            self.udp.send(datagram(body, self.token if token is None else token,
                                   self.udp_flags))

    def send(self, body: Sequence[Any], via: str) -> None:
        if via == "tcp":
            self.send_tcp(body)
        else:
            self.send_udp(body)

    # -- receiving -------------------------------------------------------------------------
    def _read_once(self, timeout: float) -> list[Packet]:
        socks = [s for s in (self.tcp, self.udp) if s is not None and not (
            s is self.tcp and self.tcp_eof)]
        if not socks:
            raise ClosedByServer("no socket left to read")
        readable, _, _ = select.select(socks, [], [], max(0.0, timeout))
        packets = []
        for sock in readable:
            if sock is self.tcp:
                data = sock.recv(1 << 16)
                if not data:
                    self.tcp_eof = True
                    continue
                packets += [to_packet(b, "tcp") for b in self._reader.feed(data)]
            else:
                try:
                    data = sock.recv(1 << 16)
                except ConnectionRefusedError:  # ICMP for an earlier datagram: nothing to read
                    continue
                _flags, token, body = parse_datagram(data)
                p = to_packet(body, "udp")
                self.udp_tags.append(p.tag)
                # Doc 3: our token, 0 on a ConnectError, a new token on a new session's ack.
                expected = {0, self.ack.token if self.ack else 0}
                if p.tag == TAG_CONNECT_ACK:
                    expected.add(p.field(2))
                if token not in expected:
                    raise ProtocolViolation(f"{p.name} datagram with a foreign token {token:#x}")
                packets.append(p)
        return packets

    def _on_heartbeat(self, p: Packet) -> None:
        """Answer at once: echo the server's stamp aged by our (tiny) holding time."""
        now = time.monotonic_ns()
        self.heartbeats_received[p.via] += 1
        echo = p.field(2, 0)
        if 0 < echo <= now:
            self.rtt_samples_ns.append(now - echo)
        if self.answer_heartbeats and p.field(1, 0):
            held = time.monotonic_ns() - now
            reply = heartbeat(time.monotonic_ns(), p.field(1) + held)
            if p.via == "tcp" and self.tcp is not None and not self.tcp_eof:
                self.send_tcp(reply)
            elif p.via == "udp" and self.udp is not None:
                self.send_udp(reply)

    def _absorb(self, p: Packet) -> None:
        """Values go to their channel's filter; everything else waits in the backlog."""
        if p.tag == TAG_HEARTBEAT:
            self._on_heartbeat(p)
            return
        if p.tag == TAG_BUNDLE:  # doc 6.16: each part as if it had come alone
            for part in p.field(1):
                self._absorb(to_packet(part, p.via))
            return
        if p.tag in (TAG_VALUE, TAG_BATCH):
            ch = p.field(1)
            rec = self.received.setdefault(ch, Received())
            rec.packets.append(p)
            if p.tag == TAG_VALUE:
                first, stamps, vals = p.field(2), [p.field(3)], [p.field(4)]
            else:
                first, stamps, vals = p.field(2), p.field(3), p.field(4)
                if len(stamps) != len(vals):
                    raise ProtocolViolation(f"batch with {len(vals)} values, {len(stamps)} stamps")
            fresh = rec.filter.accept(first, vals)
            rec.values += fresh
            rec.stamps += stamps[len(stamps) - len(fresh) :]
            return
        self.backlog.append(p)

    def pump(self, until: Callable[[], bool], timeout: float | None = None) -> bool:
        """Read and absorb packets until ``until()`` holds (True) or the deadline passes."""
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while not until():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            if self.tcp_eof and self.udp is None:
                return until()
            for p in self._read_once(left):
                self._absorb(p)
        return True

    def recv(self, match: Callable[[Packet], bool], timeout: float | None = None) -> Packet:
        """The first backlog packet (oldest first) matching ``match``; TimeoutError if none."""
        found: list[Packet] = []

        def check() -> bool:
            for i, p in enumerate(self.backlog):
                if match(p):
                    found.append(self.backlog.pop(i))
                    return True
            return False

        if not self.pump(check, timeout):
            raise TimeoutError(f"no matching packet within {timeout or self.timeout} s; "
                               f"backlog: {[p.name for p in self.backlog]}")
        return found[0]

    def recv_tag(self, *tags: int, via: str | None = None, timeout: float | None = None
                 ) -> Packet:
        return self.recv(lambda p: p.tag in tags and (via is None or p.via == via), timeout)

    def wait_eof(self, timeout: float | None = None) -> bool:
        """True once the server has closed the TCP connection."""
        return self.pump(lambda: self.tcp_eof, timeout)

    # -- session ---------------------------------------------------------------------------
    def connect_tcp(self, name: str = "independent", *, with_udp: bool = True) -> ConnectAck:
        """Doc 8.1: Hello frame, ConnectAck frame; doc 8.3: register a UDP address."""
        self.open_tcp()
        self.send_tcp(hello(name))
        p = self.recv_tag(TAG_CONNECT_ACK, TAG_CONNECT_ERROR)
        if p.tag == TAG_CONNECT_ERROR:
            raise Refused(p)
        self.ack = ConnectAck.from_packet(p)
        if with_udp:
            self.open_udp()
            self.send_udp(heartbeat(time.monotonic_ns()))
        return self.ack

    def connect_udp(self, name: str = "independent-udp", retransmit_s: float = 0.2
                    ) -> tuple[ConnectAck, int]:
        """Doc 8.2: Hello datagram with token 0, retransmitted until answered.

        Returns the ack and the token of the ack datagram's header.
        """
        sock = self.open_udp()
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            sock.send(datagram(hello(name), 0))
            ready, _, _ = select.select([sock], [], [], retransmit_s)
            if ready:
                _flags, token, body = parse_datagram(sock.recv(1 << 16))
                p = to_packet(body, "udp")
                if p.tag == TAG_CONNECT_ERROR:
                    raise Refused(p)
                if p.tag != TAG_CONNECT_ACK:
                    raise ProtocolViolation(f"hello answered with {p.name}")
                self.ack = ConnectAck.from_packet(p)
                return self.ack, token
        raise TimeoutError("no answer to the UDP hello")

    def bind(self, channel: int, direction: str, topic: str, msg_type: str,
             field: str | None = "data", transport: str = "tcp", *, via: str = "tcp",
             redundancy: int = 0, retransmit_s: float = 0.25) -> Packet:
        """Doc 9: TopicConnect, answered by TopicAck (returned) or TopicError (raised).

        Over UDP the request is retransmitted until answered (it is idempotent).
        """
        req = topic_connect(channel, direction, topic, msg_type, field, transport,
                            redundancy=redundancy)

        def answer(p: Packet) -> bool:
            return (p.tag in (TAG_TOPIC_ACK, TAG_TOPIC_ERROR) and p.field(1) == channel) or (
                p.tag == TAG_ERROR and p.field(3) in (None, channel))

        deadline = time.monotonic() + self.timeout
        while True:
            self.send(req, via)
            left = deadline - time.monotonic()
            try:
                p = self.recv(answer, min(left, retransmit_s) if via == "udp" else left)
                break
            except TimeoutError:
                if time.monotonic() >= deadline:
                    raise
        if p.tag != TAG_TOPIC_ACK:
            raise Refused(p)
        self.next_seq.setdefault(channel, 0)
        return p

    def close_channel(self, channel: int, via: str = "tcp") -> None:
        self.send([TAG_TOPIC_CLOSE, channel], via)

    def publish(self, channel: int, values: Sequence[Any], *, via: str = "tcp",
                as_batch: bool = False) -> list[int]:
        """Send ``values`` as one Batch, or one Value each; returns their stamps."""
        seq = self.next_seq.get(channel, 0)
        stamps = [time.time_ns() for _ in values]
        if as_batch:
            self.send(batch(channel, seq, stamps, values), via)
        else:
            for i, (stamp, val) in enumerate(zip(stamps, values, strict=True)):
                self.send(value(channel, seq + i, stamp, val), via)
        self.next_seq[channel] = seq + len(values)
        return stamps

    def collect(self, channel: int, count: int, timeout: float | None = None) -> list[Any]:
        """Wait until ``count`` new values arrived on ``channel``; all of them so far."""
        rec = self.received.setdefault(channel, Received())
        self.pump(lambda: len(rec.values) >= count, timeout)
        return list(rec.values)

    def stats(self, via: str = "tcp") -> dict[str, Any]:
        self.send([TAG_STATS], via)
        body: dict[str, Any] = self.recv_tag(TAG_STATS, via=via).field(1, {})
        return body

    def disconnect(self, reason: str = "bye", via: str = "tcp") -> None:
        self.send([TAG_DISCONNECT, 0, reason], via)


# -- The walk-through ------------------------------------------------------------------------

#: Float64 values whose bits must survive: subnormal, extremes, signed zero, inf, NaN.
PROBE_VALUES = [0.1, -math.pi, 5e-324, 1.7976931348623157e308, -0.0, math.inf, math.nan, 2.5]


def same_floats(a: Sequence[Any], b: Sequence[Any]) -> bool:
    """Bit-for-bit equality of two float sequences (NaN equals NaN, -0.0 is not 0.0)."""
    return len(a) == len(b) and all(
        isinstance(x, float) and isinstance(y, float)
        and struct.pack(">d", x) == struct.pack(">d", y) for x, y in zip(a, b, strict=True))


@dataclass
class ScenarioResult:
    ack: ConnectAck | None = None
    acks: dict[int, Packet] = field(default_factory=dict)
    retransmit_ack: Packet | None = None
    sent_tcp: list[float] = field(default_factory=list)
    sent_udp: list[float] = field(default_factory=list)
    got_tcp: list[Any] = field(default_factory=list)
    got_udp: list[Any] = field(default_factory=list)
    udp_filter: SequenceFilter | None = None
    topic_error: Refused | None = None
    stats: dict[str, Any] = field(default_factory=dict)
    rtt_samples_ns: list[int] = field(default_factory=list)
    heartbeats_received: dict[str, int] = field(default_factory=dict)
    closed_after_disconnect: bool = False


def run_scenario(host: str, port: int, topic: str = "/interop/f64",
                 timeout: float = 3.0) -> ScenarioResult:
    """TCP session with UDP channels on one Float64 topic; every step of the brief.

    Channels: 1 publish (TCP), 2 subscribe (TCP), 3 subscribe (UDP, redundancy 2),
    4 publish (UDP, bound with a TopicConnect sent twice over UDP), 5 an unknown type.
    """
    r = ScenarioResult()
    f64 = "std_msgs/msg/Float64"
    with IndependentClient(host, port, timeout=timeout) as c:
        r.ack = c.connect_tcp("independent-client")
        # Doc 8.3: the heartbeat datagram registered our address; a UDP Stats confirms it.
        c.stats(via="udp")
        r.acks[1] = c.bind(1, "publish", topic, f64, "data", "tcp")
        r.acks[2] = c.bind(2, "subscribe", topic, f64, "data", "tcp")
        r.acks[3] = c.bind(3, "subscribe", topic, f64, "data", "udp", redundancy=2)
        r.acks[4] = c.bind(4, "publish", topic, f64, "data", "udp", via="udp")
        # Doc 9: an identical TopicConnect is answered again with the same TopicAck.
        c.send_udp(topic_connect(4, "publish", topic, f64, "data", "udp"))
        r.retransmit_ack = c.recv_tag(TAG_TOPIC_ACK, via="udp")

        # Phase 1: Values then a Batch over TCP on channel 1.
        c.publish(1, PROBE_VALUES[:4])
        c.publish(1, PROBE_VALUES[4:], as_batch=True)
        r.sent_tcp = list(PROBE_VALUES)
        n = len(r.sent_tcp)
        c.collect(2, n)
        c.collect(3, n)
        # Phase 2: Values then a Batch over UDP on channel 4.
        udp_values = [float(i) / 8 for i in range(1, 6)]
        c.publish(4, udp_values[:2], via="udp")
        c.publish(4, udp_values[2:], via="udp", as_batch=True)
        r.sent_udp = udp_values
        r.got_tcp = c.collect(2, n + len(udp_values))
        r.got_udp = c.collect(3, n + len(udp_values))
        r.udp_filter = c.received[3].filter

        # Doc 6.6: an unknown type is refused with a TopicError for that channel.
        try:
            c.bind(5, "subscribe", topic + "_nope", "std_msgs/msg/DoesNotExist")
        except Refused as exc:
            r.topic_error = exc

        # Doc 11: give the server a period to echo our heartbeat, then read its counters.
        period = r.ack.heartbeat_ms / 1000
        c.pump(lambda: bool(c.rtt_samples_ns), 3 * period + 0.5)
        r.stats = c.stats()
        r.rtt_samples_ns = list(c.rtt_samples_ns)
        r.heartbeats_received = dict(c.heartbeats_received)

        # Doc 8.4: goodbye; the server closes the connection without answering.
        c.disconnect()
        r.closed_after_disconnect = c.wait_eof()
    return r


def main(argv: list[str]) -> int:
    host, port = (argv[1], int(argv[2])) if len(argv) > 2 else ("127.0.0.1", 7411)
    r = run_scenario(host, port)
    ok = same_floats(r.got_tcp, r.sent_tcp + r.sent_udp) and same_floats(
        r.got_udp, r.sent_tcp + r.sent_udp)
    print(f"session {r.ack.session if r.ack else '?'}: tcp {len(r.got_tcp)} values, "
          f"udp {len(r.got_udp)} values, intact={ok}, topic error="
          f"{r.topic_error.code if r.topic_error else None}, rtt samples="
          f"{len(r.rtt_samples_ns)}, closed={r.closed_after_disconnect}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
