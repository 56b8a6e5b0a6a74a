"""Protocol-level load clients: many UDP sessions driven by one thread with a selector.

The SDK spends a receive thread, a send thread and a ring per channel on every session, as a
control process should; a hundred of them in a few Python processes on a 2-core machine measure
the clients' GIL, not the server (docs/load.md shows both). These sessions speak the same wire
protocol through the same sans-IO codec (``PacketCodec``), over UDP only (the session, its
channels and its data on one socket, thesis 4.1.1), with no threads: one ticker writes every
channel of a session per tick and, between ticks, waits in ``select`` on every socket and counts
every value the moment its datagram is read (and the gaps in each subscription's sequence: the
second hop's loss), taking the latency on channel 0 of every session, as the SDK clients do.
As the SDK does, a session's tick leaves as one datagram (a ``Bundle`` of every channel) and
the session reads bundles; ``bundles=False`` in the parameters sends one ``Value`` datagram
per channel and asks for the same back (the wire behaviour before bundles, for a baseline in
the same run).

The generator shares the machine with the server it measures, so it is kept cheap: a tick is
encoded by one codec call (the ``Bundle``), not a packer call per value, and a received value
costs a sequence check, with a latency sample only on the probe channel.
"""

from __future__ import annotations

import contextlib
import selectors
import socket
import time
from collections.abc import Sequence

from rlbridge.bench.common import Params
from rlbridge.bench.load_book import F64, Book, topic
from rlbridge.wire import (
    PROTOCOL_VERSION,
    Batch,
    Bundle,
    ConnectAck,
    Hello,
    PacketCodec,
    RemoteProtocolError,
    TopicAck,
    TopicConnect,
    TopicError,
    Value,
)
from rlbridge.wire.codec import FLAG_BUNDLES
from rlbridge.wire.sequence import SequenceTracker

SUB_BASE = 1000  # subscription channel ids: SUB_BASE + c
HANDSHAKE_S = 60.0
#: Values per bundle the clients send: ~20 bytes each, well inside a 1,400-byte datagram.
PARTS_PER_DATAGRAM = 50


class _RawSession(Book):
    def __init__(self, params: Params, index: int, phase: list[str], codec: PacketCodec) -> None:
        super().__init__(index, phase)
        self.codec = codec
        self.n = int(params["channels"])
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        with contextlib.suppress(OSError):
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock.connect((params["host"], int(params["port"])))
        self.token = 0
        self.seq = 0
        self._received = 0
        self.send_errors = 0
        self.trackers = {SUB_BASE + c: SequenceTracker() for c in range(self.n)}
        self.bundles = bool(params.get("bundles", True))
        self.flags = FLAG_BUNDLES if self.bundles else 0
        self._handshake()
        self.sock.setblocking(False)
        self.encode = codec.encode_datagram

    def _exchange(self, packets: dict[int, TopicConnect | Hello], token: int) -> dict[int, object]:
        """Send ``packets`` (by key) until each has its answer; UDP may lose either way."""
        answers: dict[int, object] = {}
        deadline = time.monotonic() + HANDSHAKE_S
        while len(answers) < len(packets):
            if time.monotonic() > deadline:
                raise TimeoutError(f"load-{self.index}: no answer from the server")
            for key, packet in packets.items():
                if key not in answers:
                    self.sock.send(self.codec.encode_datagram(packet, token, self.flags))
            self.sock.settimeout(1.0)
            with contextlib.suppress(TimeoutError):
                while len(answers) < len(packets):
                    _f, _t, reply = self.codec.decode_datagram(self.sock.recv(1 << 16))
                    if isinstance(reply, ConnectAck):
                        answers[0] = reply
                    elif isinstance(reply, TopicAck | TopicError):
                        answers[reply.channel] = reply
        return answers

    def _handshake(self) -> None:
        ack = self._exchange({0: Hello(PROTOCOL_VERSION, f"load-{self.index}")}, 0)[0]
        assert isinstance(ack, ConnectAck)
        self.token = ack.token
        requests: dict[int, TopicConnect | Hello] = {}
        for c in range(self.n):
            name = topic(self.index, c)
            requests[SUB_BASE + c] = TopicConnect(SUB_BASE + c, "subscribe", name, F64,
                                                  transport="udp")
            requests[1 + c] = TopicConnect(1 + c, "publish", name, F64, transport="udp")
        for reply in self._exchange(requests, self.token).values():
            if isinstance(reply, TopicError):
                raise RuntimeError(f"load-{self.index}: {reply.reason}")

    def received(self) -> int:
        return self._received

    def extra(self) -> Params:
        return {"lost_seq": sum(t.lost for t in self.trackers.values()),
                "overwritten": 0, "send_errors": self.send_errors}

    def _send(self, datagram: bytes) -> None:
        try:
            self.sock.send(datagram)
        except OSError:  # a full socket buffer (ENOBUFS/EAGAIN): not sent, counted
            self.send_errors += 1

    def write_all(self, stamp: float) -> None:
        seq, encode, token, flags = self.seq, self.encode, self.token, self.flags
        values: list[Value | Batch] = [Value(c, seq, 0, stamp) for c in range(1, self.n + 1)]
        if self.bundles:
            for i in range(0, self.n, PARTS_PER_DATAGRAM):
                chunk = values[i : i + PARTS_PER_DATAGRAM]
                self._send(encode(Bundle(chunk) if len(chunk) > 1 else chunk[0], token, flags))
        else:
            for v in values:
                self._send(encode(v, token, flags))
        self.seq = seq + 1
        self.sent += self.n

    def drain(self) -> None:
        decode, now = self.codec.decode_datagram, time.time
        while True:
            try:
                data = self.sock.recv(1 << 16)
            except (BlockingIOError, InterruptedError):
                return
            t = now()
            try:
                _f, _t, packet = decode(data)
            except RemoteProtocolError:
                continue
            if isinstance(packet, Bundle):
                self._take(packet.parts, t)
            elif isinstance(packet, Value | Batch):
                self._take((packet,), t)

    def _take(self, parts: Sequence[Value | Batch], t: float) -> None:
        trackers, got = self.trackers, 0
        for part in parts:
            tracker = trackers.get(part.channel)
            if tracker is None:
                continue
            values: Sequence[float]
            if isinstance(part, Value):
                values, first = (part.value,), part.seq
            else:
                values, first = part.values, part.first_seq
            start = tracker.accept_run(first, len(values))
            got += len(values) - start
            if part.channel == SUB_BASE:  # the probe channel: latency of every new value
                for v in values[start:]:
                    self.record((t - v) * 1e6)
        self._received += got

    def close(self) -> None:
        self.sock.close()


class RawSessions:
    """Every raw session of this process, and the wait between ticks that reads them."""

    def __init__(self, params: Params, phase: list[str]) -> None:
        codec = PacketCodec()
        self.sessions = [_RawSession(params, i, phase, codec) for i in params["ids"]]
        self._selector = selectors.DefaultSelector()
        for s in self.sessions:
            self._selector.register(s.sock, selectors.EVENT_READ, s)

    def wait_until(self, deadline: float) -> None:
        while True:
            left = deadline - time.monotonic()
            for key, _ in self._selector.select(max(0.0, left)):
                key.data.drain()
            if left <= 0:
                return
