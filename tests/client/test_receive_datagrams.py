"""The receive thread's datagram path: a bundle's short path against the general one, the drain.

A real :class:`~rlbridge.client.session.connection.Connection` (not opened: no server needed) gets
a UDP
socket connected to a socket of the test, which plays the server and sends real datagrams.
The receiver reads them as its thread does after ``poll``: ``_receive_datagrams`` with the
UDP-only "is another one queued?" poll, then ``_flush_values`` at the end of the wake-up.

* The same parts (values and batches of two channels, a gap, a duplicate) arrive once as one
  ``Bundle`` (the short path: ``Receiver._bundle``) and once as one datagram each (the general
  path: ``_dispatch``): the runs handed to ``on_values`` must be the same.
* One wake-up reads what is queued (one datagram without a failing ``recv``, or several), and
  hands values on every ``RUN_DATAGRAMS`` datagrams; bad datagrams are counted, not fatal.
"""

from __future__ import annotations

import select
import socket
import time
from collections.abc import Callable, Iterator

import pytest

from rlbridge.client.session.connection import Connection
from rlbridge.client.session.receiver import RUN_DATAGRAMS, Receiver
from rlbridge.wire import Batch, Bundle, Packet, PacketCodec, Value
from rlbridge.wire.link import LinkMonitor

TOKEN = 0x1234_5678
Run = tuple[int, int, list[int], list[object]]


class Session:
    """A connection's UDP side wired to a socket of the test, and its receiver."""

    def __init__(self) -> None:
        self.server = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.server.bind(("127.0.0.1", 0))
        self.conn = Connection("127.0.0.1", self.server.getsockname()[1], name="recv-test",
                               nodelay=True, control="tcp", timeout=5.0)
        self.client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.client.connect(self.server.getsockname())
        self.server.connect(self.client.getsockname())
        self.conn.udp = self.client
        self.conn.link = LinkMonitor(time.monotonic_ns(), 100_000_000)
        self.runs: list[Run] = []
        self.conn.on_values = lambda ch, first, stamps, values: self.runs.append(
            (ch, first, list(stamps), list(values)))
        self.receiver = Receiver(self.conn, 0, [], self.conn._wake_r)
        poller = select.poll()
        poller.register(self.client, select.POLLIN)
        self.queued: Callable[[int], list[tuple[int, int]]] = poller.poll
        self.codec = PacketCodec()

    def send(self, packet: Packet, token: int = TOKEN) -> None:
        self.server.send(self.codec.encode_datagram(packet, token))

    def wake_up(self) -> None:
        """What the receive thread does once ``poll`` says the UDP socket is readable."""
        assert select.select([self.client], [], [], 5.0)[0], "nothing arrived"
        self.receiver._receive_datagrams(self.client, TOKEN, self.queued)

    def queue_is_empty(self) -> bool:
        return not self.queued(0)

    def close(self) -> None:
        for sock in (self.server, self.client, self.conn._wake_r, self.conn._wake_w):
            sock.close()


@pytest.fixture
def session() -> Iterator[Callable[[], Session]]:
    made: list[Session] = []

    def make() -> Session:
        made.append(Session())
        return made[-1]

    yield make
    for s in made:
        s.close()


def _settle() -> None:
    """Loopback queues a datagram within its ``send`` on Linux; a moment more, for safety, so
    that the whole burst is queued before the wake-up reads it (nothing here is timed)."""
    time.sleep(0.05)


PARTS: list[Value | Batch] = [
    Value(1, 0, 10, 1.0),
    Value(2, 0, 11, 2.0),
    Batch(1, 1, [12, 13], [3.0, 4.0]),  # continues channel 1's run
    Value(1, 6, 14, 5.0),  # a gap: channel 1's run so far is handed on, a new one starts
    Value(2, 0, 11, 2.0),  # a duplicate: a new run (the channel's tracker drops it)
    Value(2, 1, 15, 6.0),  # continues the new run
]
#: What ``on_values`` gets for PARTS, whether bundled or not.
EXPECTED: list[Run] = [
    (1, 0, [10, 12, 13], [1.0, 3.0, 4.0]),
    (2, 0, [11], [2.0]),
    (1, 6, [14], [5.0]),
    (2, 0, [11, 15], [2.0, 6.0]),
]


def test_a_bundle_hands_on_the_same_runs_as_its_parts_one_datagram_each(
        session: Callable[[], Session]) -> None:
    bundled, alone = session(), session()
    bundled.send(Bundle(PARTS))
    for part in PARTS:
        alone.send(part)
    for s in (bundled, alone):
        rx_before = s.conn.link._last_rx  # type: ignore[union-attr]
        _settle()  # every datagram queued before the wake-up: one read burst
        s.wake_up()
        s.receiver._flush_values()
        assert s.queue_is_empty()
        assert s.conn.link._last_rx > rx_before  # type: ignore[union-attr]
        assert not s.conn.datagrams_dropped
    assert bundled.runs == EXPECTED
    assert alone.runs == EXPECTED


def test_one_datagram_is_read_without_a_failing_recv_and_a_burst_to_the_end(
        session: Callable[[], Session]) -> None:
    s = session()
    s.send(Bundle([Value(1, 0, 10, 1.0), Value(2, 0, 10, 2.0)]))
    s.wake_up()
    assert s.queue_is_empty()
    s.receiver._flush_values()
    assert s.runs == [(1, 0, [10], [1.0]), (2, 0, [10], [2.0])]
    s.runs.clear()
    burst = 5
    for seq in range(burst):
        s.send(Bundle([Value(1, 1 + seq, 20 + seq, float(seq))]))
    _settle()
    s.wake_up()
    assert s.queue_is_empty()
    s.receiver._flush_values()
    assert s.runs == [(1, 1, [20 + k for k in range(burst)], [float(k) for k in range(burst)])]


def test_a_long_burst_is_handed_on_every_run_datagrams(session: Callable[[], Session]) -> None:
    s = session()
    count = RUN_DATAGRAMS + 8
    for seq in range(count):
        s.send(Value(3, seq, seq, float(seq)))
    _settle()
    s.wake_up()
    assert [(ch, first, len(values)) for ch, first, _, values in s.runs] == [
        (3, 0, RUN_DATAGRAMS)]
    s.receiver._flush_values()
    assert [(ch, first, len(values)) for ch, first, _, values in s.runs] == [
        (3, 0, RUN_DATAGRAMS), (3, RUN_DATAGRAMS, 8)]


def test_bad_datagrams_are_counted_and_the_good_ones_still_read(
        session: Callable[[], Session]) -> None:
    s = session()
    s.send(Value(1, 0, 10, 1.0), token=TOKEN + 1)  # another session's token
    s.server.send(b"\x00" * 3)  # shorter than a header
    s.send(Bundle([Value(1, 0, 10, 1.0)]))
    _settle()
    s.wake_up()
    s.receiver._flush_values()
    assert s.queue_is_empty()
    assert s.conn.datagrams_dropped["bad_token"] == 1
    assert sum(s.conn.datagrams_dropped.values()) == 2
    assert s.runs == [(1, 0, [10], [1.0])]
