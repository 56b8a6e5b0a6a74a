"""Protocol-level load clients: many UDP sessions driven by one thread with a selector.

The SDK spends a receive thread, a send thread and a ring per channel on every session, as a
control process should; a hundred of them in a few Python processes on a 2-core machine measure
the clients' GIL, not the server (docs/load.md shows both). These sessions speak the same wire
protocol through the same sans-IO codec (``PacketCodec``), over UDP only (the session, its
channels and its data on one socket, thesis 4.1.1), with no threads: one ticker writes a
``Value`` datagram per channel per tick and, between ticks, waits in ``select`` on every socket
and takes the latency of each value the moment its datagram is read.
"""

from __future__ import annotations

import contextlib
import selectors
import socket
import time

from rlbridge.bench.common import Params
from rlbridge.bench.load_book import F64, Book, topic
from rlbridge.wire import (
    PROTOCOL_VERSION,
    Batch,
    ConnectAck,
    Hello,
    PacketCodec,
    RemoteProtocolError,
    TopicAck,
    TopicConnect,
    TopicError,
    Value,
)
from rlbridge.wire.sequence import SequenceTracker

SUB_BASE = 1000  # subscription channel ids: SUB_BASE + c
HANDSHAKE_S = 60.0


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
        self._handshake()
        self.sock.setblocking(False)

    def _exchange(self, packets: dict[int, TopicConnect | Hello], token: int) -> dict[int, object]:
        """Send ``packets`` (by key) until each has its answer; UDP may lose either way."""
        answers: dict[int, object] = {}
        deadline = time.monotonic() + HANDSHAKE_S
        while len(answers) < len(packets):
            if time.monotonic() > deadline:
                raise TimeoutError(f"load-{self.index}: no answer from the server")
            for key, packet in packets.items():
                if key not in answers:
                    self.sock.send(self.codec.encode_datagram(packet, token))
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

    def write_all(self, stamp: float) -> None:
        encode, send, token, seq = self.codec.encode_datagram, self.sock.send, self.token, self.seq
        for c in range(1, self.n + 1):
            try:
                send(encode(Value(c, seq, 0, stamp), token))
            except OSError:  # a full socket buffer (ENOBUFS/EAGAIN): not sent, counted
                self.send_errors += 1
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
            if isinstance(packet, Value):
                values, first = [packet.value], packet.seq
            elif isinstance(packet, Batch):
                values, first = packet.values, packet.first_seq
            else:
                continue
            tracker = self.trackers.get(packet.channel)
            if tracker is None:
                continue
            start = tracker.accept_run(first, len(values))
            for v in values[start:]:
                self.record((t - v) * 1e6)
            self._received += len(values) - start

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
