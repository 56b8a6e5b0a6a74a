"""The send thread outlives a session that ends under one of its rounds.

A round takes values, then hands them to the session's sockets; when the session ends in
between (the receive thread saw the server go, the supervisor closed the sockets to open new
ones), the send to the closed session raises ``ConnectionClosed``. That must cost that round
only: the thread has to be alive for the reconnect supervisor, which resumes it on the next
session. Real server, real sockets; the session is ended from inside the round, where the
race puts it.
"""

from __future__ import annotations

import threading

from link_helpers import WAIT, roundtrip

from rlbridge.client.bridge import Bridge
from rlbridge.client.channels.pacing import Pacing
from rlbridge.client.session.reconnect import Backoff
from rlbridge.server import ServerThread
from waiting import wait_until

F64 = "std_msgs/msg/Float64"
FAST = Backoff(initial=0.02, max_delay=0.2)


class EndsTheSession:
    """An outgoing source whose ``take`` ends the session and closes its sockets, once.

    It then hands over one value for a channel that exists, so the round goes on to send on
    a session that has no sockets any more.
    """

    transport = "udp"
    immediate = True
    latest = False
    pacing: Pacing | None = None
    deferred = False
    holding = False

    def __init__(self, bridge: Bridge, channel_id: int) -> None:
        self.channel_id = channel_id
        self._conn = bridge._conn
        self.fired = threading.Event()

    def take(self, congested: bool = False) -> tuple[int, list[int], list[object], int]:
        if self.fired.is_set():
            return 0, [], [], 0
        self.fired.set()
        conn = self._conn
        conn.end_session("test: ended under a send round", conn._generation)
        conn._close_session_sockets()  # what the supervisor's reopen does first
        return 0, [0], [1.0], 0

    def pending(self) -> int:
        return 0 if self.fired.is_set() else 1

    def ready(self, now_ns: int) -> bool:
        return not self.fired.is_set()

    def retry_in(self, now_ns: int) -> float | None:
        return None

    def refused(self, count: int) -> None:
        pass

    def left_out(self, count: int) -> None:
        pass


def test_send_thread_survives_a_session_closed_under_its_round(server: ServerThread) -> None:
    with Bridge.connect("127.0.0.1", server.port, name="sender", reconnect=FAST) as pub, \
            Bridge.connect("127.0.0.1", server.port, name="reader") as sub:
        inbox = sub.subscribe("/sendthread", F64, transport="udp", blocking=True)
        out = pub.publish("/sendthread", F64, transport="udp")
        assert roundtrip(out, inbox, 1.0)
        sender = pub._sender
        thread_id = sender.native_id
        errors = sender.send_errors
        source = EndsTheSession(pub, out.channel_id)
        sender.add(source)
        sender.doorbell.ring()
        assert source.fired.wait(WAIT)
        wait_until(lambda: sender.send_errors > errors,
                   "the failed send to be counted", timeout=WAIT)
        sender.remove(source)
        assert sender.native_id == thread_id, "the send thread ended with the session"
        wait_until(lambda: pub.reconnects >= 1,
                   "the supervisor to open a new session", timeout=WAIT)
        assert roundtrip(out, inbox, 2.0), "values flow again on the new session"
        assert sender.native_id == thread_id


def test_send_takes_no_lock_on_the_control_loops_path(server: ServerThread) -> None:
    """``send()`` (no wait) neither takes the lock that ``send(wait=True)`` waits under nor
    blocks: another thread holds that lock, and the values still go."""
    with Bridge.connect("127.0.0.1", server.port, name="nolock") as pub, \
            Bridge.connect("127.0.0.1", server.port, name="reader") as sub:
        inbox = sub.subscribe("/nolock", F64, transport="udp", blocking=True)
        out = pub.publish("/nolock", F64, transport="udp", through_buffer=True)
        sent = threading.Event()
        with pub._sender._flushed:  # held by this thread while the loop's thread sends
            def loop() -> None:
                out.write(2.0)
                pub.send()
                sent.set()

            t = threading.Thread(target=loop)
            t.start()
            assert sent.wait(WAIT), "send() waited for the flush lock"
            t.join(WAIT)
        assert inbox.read(timeout=WAIT) == 2.0


class FlushesDuringItsTake:
    """A source with a policy (not plain) whose first ``take`` writes a value into a buffered
    channel and asks for a flush, as a second thread calling ``send()`` mid-round would."""

    transport = "udp"
    immediate = False
    latest = False
    pacing: Pacing | None = None
    deferred = False
    holding = False
    channel_id = 10_000

    def __init__(self, bridge: Bridge, out: object) -> None:
        self._bridge, self._out = bridge, out
        self.fired = threading.Event()

    def take(self, congested: bool = False) -> tuple[int, list[int], list[object], int]:
        if not self.fired.is_set():
            self.fired.set()
            self._out.write(3.0)  # type: ignore[attr-defined]
            self._bridge.send()
        return 0, [], [], 0

    def pending(self) -> int:
        return 0

    def ready(self, now_ns: int) -> bool:
        return False

    def retry_in(self, now_ns: int) -> float | None:
        return None

    def refused(self, count: int) -> None:
        pass

    def left_out(self, count: int) -> None:
        pass


def test_a_flush_asked_during_a_round_gets_a_round_of_its_own(server: ServerThread) -> None:
    with Bridge.connect("127.0.0.1", server.port, name="midround") as pub, \
            Bridge.connect("127.0.0.1", server.port, name="reader") as sub:
        inbox = sub.subscribe("/midround", F64, transport="udp", blocking=True)
        # Written only from inside the round (the send thread is its one writer).
        late = pub.publish("/midround", F64, transport="udp", through_buffer=True)
        source = FlushesDuringItsTake(pub, late)
        pub._sender.add(source)
        try:
            pub.send()  # this round's take writes 3.0 and asks again: a second round sends it
            assert source.fired.wait(WAIT)
            assert inbox.read(timeout=WAIT) == 3.0
        finally:
            pub._sender.remove(source)
