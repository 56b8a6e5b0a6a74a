"""``Bridge.send(inline=True)``: the round in the caller's thread, when that is safe.

What the mechanism promises (docs/concepts.md, "Sending"): values sent inline leave in order
with consecutive sequence numbers; an inline round never overlaps another round (the send
thread's or a second caller's), so no channel's values are reordered or lost; the send thread
is not woken for a round that went inline; and whatever cannot go inline (TCP channels,
channels with policies, sealed or unbundled sessions, a round larger than a datagram, a full
socket buffer) goes through the send thread as before. Real server, real sockets; the stress
test records each datagram on its way into the real socket to check its order.
"""

from __future__ import annotations

import errno
import socket
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from link_helpers import WAIT

from rlbridge import Policy, Psk, RealTimeWarning, Tuning
from rlbridge.client.bridge import Bridge
from rlbridge.client.channels.incoming import IncomingChannel, OutgoingChannel
from rlbridge.client.session.connection import Connection
from rlbridge.client.session.sender import SendLoop
from rlbridge.csp.process import Code
from rlbridge.server import ServerThread
from rlbridge.wire import Batch, Bundle, Value
from rlbridge.wire.bundle import DatagramPacker
from rlbridge.wire.codec import PacketCodec
from waiting import wait_until

F64 = "std_msgs/msg/Float64"
STR = "std_msgs/msg/String"


def arrived(out: OutgoingChannel, inbox: IncomingChannel, bridge: Bridge) -> None:
    """Warm-up: write -1 and send it inline until it arrives (the bindings are in place)."""
    def once() -> bool:
        out.write(-1.0)
        bridge.send(inline=True)
        try:
            return bool(inbox.read(timeout=0.2) == -1.0)
        except TimeoutError:
            return False
    wait_until(once, "a first value through the server", timeout=WAIT)


def read_until(inbox: IncomingChannel, last: float) -> list[float]:
    """What arrives until ``last`` does (bounded by ``WAIT``)."""
    got: list[float] = []

    def done() -> bool:
        got.extend(inbox.read_many())
        return bool(got) and got[-1] == last

    wait_until(done, f"value {last}", timeout=WAIT)
    return got


def thread_done(sender: SendLoop, rounds: int) -> None:
    """Wait until the send thread has run ``rounds`` rounds and left the last one (it holds
    the round lock until then, and an inline ``send`` in that moment rings it instead)."""
    wait_until(lambda: sender.rounds >= rounds and not sender._round.locked(),
               "the send thread's round to end", timeout=WAIT)


class Recorder:
    """Every value datagram the session hands its UDP socket, decoded, in the order sent.

    Installed under the round lock and with a fresh packer, so every round after it sends
    through the recorder; each datagram still goes to the real socket.
    """

    def __init__(self, bridge: Bridge) -> None:
        conn, sender = bridge._conn, bridge._sender
        self.codec = PacketCodec()
        self.datagrams: list[bytes] = []
        self._lock = threading.Lock()
        send = conn.send_udp

        def record(data: bytes, flags: int = 0) -> None:
            send(data, flags)  # raises (EAGAIN) before the datagram counts as sent
            with self._lock:
                self.datagrams.append(data)

        with sender._round:
            conn.send_udp = record  # type: ignore[method-assign]
            sender._packer = None  # the next round makes one that sends through us

    def values(self) -> dict[int, list[tuple[int, Any]]]:
        """Per channel: (sequence number, value) in the order the datagrams left."""
        seen: dict[int, list[tuple[int, Any]]] = {}
        for data in list(self.datagrams):
            packet = self.codec.decode_datagram(data)[2]
            parts = packet.parts if isinstance(packet, Bundle) else [packet]
            for part in parts:
                if isinstance(part, Value):
                    seen.setdefault(part.channel, []).append((part.seq, part.value))
                elif isinstance(part, Batch):
                    seen.setdefault(part.channel, []).extend(
                        (part.first_seq + i, v) for i, v in enumerate(part.values))
        return seen


@pytest.fixture
def pair(server: ServerThread) -> Iterator[tuple[Bridge, Bridge]]:
    with Bridge.connect("127.0.0.1", server.port, name="inline-pub") as pub, \
            Bridge.connect("127.0.0.1", server.port, name="inline-sub") as sub:
        yield pub, sub


def test_inline_values_arrive_in_order_and_the_send_thread_sleeps(
        pair: tuple[Bridge, Bridge]) -> None:
    pub, sub = pair
    topics = ("/inline/a", "/inline/b")
    inboxes = [sub.subscribe(t, F64, transport="udp", blocking=True, buffer_size=512)
               for t in topics]
    outs = [pub.publish(t, F64, transport="udp", through_buffer=True) for t in topics]
    for out, inbox in zip(outs, inboxes, strict=True):
        arrived(out, inbox, pub)
    sender = pub._sender
    recorder = Recorder(pub)
    count = 300
    for i in range(count):
        for out in outs:
            out.write(float(i))
        pub.send(inline=True)
        if i % 50 == 0:  # let the subscriber's thread drain (loopback, no loss to blame)
            inboxes[0].read(timeout=WAIT)
            inboxes[1].read(timeout=WAIT)
    # Nothing woke the send thread: every round of this session went inline.
    assert sender.rounds == 0
    assert sender.inline_fallbacks == 0
    assert sender.inline_rounds >= count
    sent = recorder.values()
    for out in outs:
        seqs = [s for s, _ in sent[out.channel_id]]
        assert seqs == list(range(seqs[0], seqs[0] + count))  # consecutive, in order
        assert [v for _, v in sent[out.channel_id]] == [float(i) for i in range(count)]
    for inbox in inboxes:  # and they arrived, in order, through the real server
        got = read_until(inbox, float(count - 1))
        assert got == sorted(got)
        assert inbox.lost == 0


def test_two_inline_callers_and_paced_rounds_never_overlap(server: ServerThread) -> None:
    """Two threads write their own channels and send inline while the send loop ticks at
    2 kHz: every channel's values leave exactly once, in order, with consecutive sequence
    numbers (an overlapping round would reorder or repeat them), and both paths ran."""
    with Bridge.connect("127.0.0.1", server.port, name="inline-stress",
                        send_rate_hz=2000) as pub:
        outs = [pub.publish(f"/inline/stress{i}", F64, transport="udp", through_buffer=True,
                            buffer_size=8192) for i in range(4)]
        sender = pub._sender
        recorder = Recorder(pub)
        count = 3000
        start = threading.Barrier(2)

        def caller(mine: list[OutgoingChannel]) -> None:
            start.wait(WAIT)
            for i in range(count):
                for out in mine:
                    out.write(float(i))
                pub.send(inline=True)

        threads = [threading.Thread(target=caller, args=(outs[k::2],)) for k in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(WAIT * 3)
            assert not t.is_alive()
        pub.send(wait=True)  # what waits goes out through the thread
        wait_until(lambda: all(len(recorder.values().get(o.channel_id, ())) == count
                               for o in outs), "every value recorded", timeout=WAIT)
        sent = recorder.values()
        for out in outs:
            seqs = [s for s, _ in sent[out.channel_id]]
            assert seqs == list(range(seqs[0], seqs[0] + count))
            assert [v for _, v in sent[out.channel_id]] == [float(i) for i in range(count)]
            assert out.statistics().overwritten == 0
        assert sender.inline_rounds > 0
        assert sender.rounds > 0


@pytest.mark.parametrize(("transport", "policy"), [
    ("tcp", Policy()),
    ("udp", Policy(max_rate_hz=1000.0)),
    ("udp", Policy(latest=True)),
    ("udp", Policy(redundancy=1)),
    ("udp", Policy(max_age_ms=1000)),
])
def test_a_channel_with_a_policy_or_tcp_goes_through_the_thread(
        pair: tuple[Bridge, Bridge], transport: str, policy: Policy) -> None:
    """The plain channel goes inline; the other one is the send thread's, which is rung only
    when that channel has something to send."""
    pub, sub = pair
    inbox = sub.subscribe("/inline/policy", F64, transport=transport, blocking=True,
                          buffer_size=64)
    plain_inbox = sub.subscribe("/inline/plain", F64, transport="udp", blocking=True)
    plain = pub.publish("/inline/plain", F64, transport="udp", through_buffer=True)
    other = pub.publish("/inline/policy", F64, through_buffer=True, transport=transport,
                        policy=policy)
    sender = pub._sender
    arrived(plain, plain_inbox, pub)
    rounds, fallbacks = sender.rounds, sender.inline_fallbacks
    assert fallbacks == 0  # nothing waited in the other channel: the thread slept
    assert rounds == 0
    other.write(7.0)
    plain.write(1.0)
    pub.send(inline=True)
    assert plain_inbox.read(timeout=WAIT) == 1.0
    assert inbox.read(timeout=WAIT) == 7.0
    assert sender.inline_fallbacks == fallbacks + 1
    wait_until(lambda: sender.rounds > rounds, "the send thread's round", timeout=WAIT)


def test_flow_controlled_incoming_channels_do_not_stop_inline_rounds(
        pair: tuple[Bridge, Bridge]) -> None:
    """Credit is granted by the send thread when a reader consumed enough (its read rings
    the thread): an inline round neither needs it nor keeps it from happening."""
    pub, sub = pair
    status = pub.subscribe("/inline/status", "std_msgs/msg/String", transport="tcp",
                           blocking=True, buffer_size=4)  # flow control on by default
    writer = sub.publish("/inline/status", "std_msgs/msg/String", transport="tcp")
    inbox = sub.subscribe("/inline/withflow", F64, transport="udp", blocking=True)
    out = pub.publish("/inline/withflow", F64, transport="udp", through_buffer=True)
    arrived(out, inbox, pub)
    assert pub._sender.inline_rounds >= 1
    assert pub._sender.inline_fallbacks == 0
    for i in range(12):  # three times the buffer: only credit lets them all through
        writer.write(f"s{i}")
        assert status.read(timeout=WAIT) == f"s{i}"


def test_a_hard_real_time_process_never_sends_inline(pair: tuple[Bridge, Bridge]) -> None:
    """The HRT rule holds where the SDK can see it: a process marked ``hrt`` gets the send
    thread (and one warning), not a system call for the network in its own thread."""
    pub, sub = pair
    inbox = sub.subscribe("/inline/hrt", F64, transport="udp", blocking=True)
    out = pub.publish("/inline/hrt", F64, transport="udp", through_buffer=True)

    def tick() -> None:
        out.write(5.0)
        pub.send(inline=True)

    with pytest.warns(RealTimeWarning, match="send\\(inline=True\\)"):
        Code(tick, name="loop", hrt=True).run()
    assert inbox.read(timeout=WAIT) == 5.0
    assert pub._sender.inline_rounds == 0
    thread_done(pub._sender, 1)
    tick()  # the same call outside an HRT process goes inline
    assert inbox.read(timeout=WAIT) == 5.0
    assert pub._sender.inline_rounds == 1


@pytest.mark.parametrize("sealed", [False, True])
def test_sealed_or_unbundled_sessions_fall_back(make_server: Callable[..., ServerThread],
                                                tmp_path: Path, sealed: bool) -> None:
    """A sealed session's datagrams are sealed on the send thread; an unbundled one sends a
    datagram per channel: neither goes inline, and the values still arrive."""
    key = bytes(range(32))
    options: dict[str, Any] = ({"security": Psk(key=key)} if sealed
                               else {"tuning": Tuning(bundles=False)})
    if sealed:
        (tmp_path / "keys").write_text(key.hex() + "\n")
    server = make_server(psk_file=tmp_path / "keys") if sealed else make_server()
    with Bridge.connect("127.0.0.1", server.port, name="inline-fb", **options) as pub, \
            Bridge.connect("127.0.0.1", server.port, name="inline-fb-sub",
                           security=Psk(key=key) if sealed else None) as sub:
        inbox = sub.subscribe("/inline/fallback", F64, transport="udp", blocking=True)
        out = pub.publish("/inline/fallback", F64, transport="udp", through_buffer=True)
        out.write(3.0)
        pub.send(inline=True)
        assert inbox.read(timeout=WAIT) == 3.0
        assert pub._sender.inline_rounds == 0
        assert pub._sender.inline_fallbacks >= 1


def test_a_round_larger_than_a_datagram_is_handed_to_the_thread_in_order(
        pair: tuple[Bridge, Bridge]) -> None:
    pub, sub = pair
    inbox = sub.subscribe("/inline/big", STR, transport="udp", blocking=True, buffer_size=64)
    out = pub.publish("/inline/big", STR, transport="udp", through_buffer=True,
                      buffer_size=64)
    sender = pub._sender
    big = ["x" * 600 + str(i) for i in range(4)]  # ~2.4 kB: more than one datagram
    for value in big:
        out.write(value)
    pub.send(inline=True)
    got = [inbox.read(timeout=WAIT) for _ in big]
    assert got == big
    assert sender.inline_handoffs == 1
    assert sender.inline_rounds == 0
    thread_done(sender, 1)
    out.write("small")  # the next round fits: inline again
    pub.send(inline=True)
    assert inbox.read(timeout=WAIT) == "small"
    assert sender.inline_rounds == 1


def test_a_full_socket_buffer_hands_the_round_over_and_loses_nothing(
        pair: tuple[Bridge, Bridge]) -> None:
    """``EAGAIN`` cannot be provoked on loopback (its datagrams leave the send buffer at
    once), so the non-blocking send is made to report it for a while; the real socket
    then carries the rounds the send thread took over, in order."""
    pub, sub = pair
    inbox = sub.subscribe("/inline/full", F64, transport="udp", blocking=True, buffer_size=64)
    out = pub.publish("/inline/full", F64, transport="udp", through_buffer=True)
    arrived(out, inbox, pub)
    conn, sender = pub._conn, pub._sender
    full = {"left": 3}
    real = conn.send_udp

    def sometimes_full(data: bytes, flags: int = 0) -> None:
        if full["left"] and flags & socket.MSG_DONTWAIT:  # only a send that must not wait
            full["left"] -= 1
            raise BlockingIOError(errno.EAGAIN, "Resource temporarily unavailable")
        real(data, flags)

    conn.send_udp = sometimes_full  # type: ignore[method-assign]
    for i in range(10):
        out.write(float(i))
        pub.send(inline=True)
    got = read_until(inbox, 9.0)
    assert got == [float(i) for i in range(10)]
    assert sender.inline_handoffs >= 1
    assert sender.send_errors == 0
    assert inbox.lost == 0


def test_a_handed_over_round_of_an_ended_session_is_counted() -> None:
    """The hand-over is for the packer (session) it was taken for; a new session's round
    counts it as a failed round instead of sending old sequence numbers."""
    # A send loop of a connection never opened (its thread never started); real packers: the
    # compiled module (rlbridge/_compiled.py) checks the types of what it is given.
    conn = Connection("127.0.0.1", 9, name="handoff", nodelay=True, control="tcp", timeout=5.0)
    loop = SendLoop(conn, rate_hz=None, max_batch=64)
    old, new = (DatagramPacker(PacketCodec(), 1, 1400, lambda _: None) for _ in range(2))
    loop._handoff = (old, [("part",)])
    parts: list[Any] = []
    loop._take_handoff(new, parts)
    assert parts == []
    assert loop.send_errors == 1
    assert loop._handoff is None
    loop._handoff = (new, [("part",)])
    loop._take_handoff(new, parts)
    assert parts == [("part",)]
    assert loop.send_errors == 1
    conn._wake_r.close()
    conn._wake_w.close()
