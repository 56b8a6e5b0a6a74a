"""Reconnect: the backoff policy, then a real ``rlbridge serve`` killed and restarted under
the SDK, which resumes by itself (channels bound again, values flowing both ways on TCP and UDP,
values written during the outage sent afterwards), plus link events, fail-safes and ``close``
in every phase of a reconnect.
"""

from __future__ import annotations

import contextlib
import os
import random
import socket
import subprocess
import threading
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from link_helpers import WAIT, roundtrip

from rlbridge import LinkLost, Policy, Psk, Tuning, WouldBlock
from rlbridge.client.bridge import Bridge
from rlbridge.client.channels.failsafe import SafeValue
from rlbridge.client.session.link_events import LinkEvent
from rlbridge.client.session.reconnect import Backoff, ClientState
from rlbridge.errors import ChannelClosed
from rlbridge.wire.link import LinkState
from waiting import assert_running, wait_until, wait_until_ok

F64 = "std_msgs/msg/Float64"
I32 = "std_msgs/msg/Int32"
#: Quick retries, so that a restarted server is found again soon after it listens.
FAST = Backoff(initial=0.02, max_delay=0.2)


# -- the policy ----------------------------------------------------------------------------


def test_backoff_grows_caps_and_jitters_within_bounds() -> None:
    exact = Backoff(initial=0.1, max_delay=1.0, factor=2.0, jitter=0.0)
    assert [exact.next_delay(a) for a in range(6)] == pytest.approx(
        [0.1, 0.2, 0.4, 0.8, 1.0, 1.0])
    assert exact.next_delay(10_000) == 1.0  # no overflow after a day of attempts
    rng = random.Random(7)
    jittered = Backoff(initial=0.1, max_delay=1.0, jitter=0.5, rand=rng.random)
    delays = [jittered.next_delay(a) for a in range(200)]
    assert all(0 < d <= 1.0 for d in delays)
    assert min(delays[10:]) >= 0.5  # at the cap: shortened by at most half
    assert len({round(d, 9) for d in delays[10:]}) > 100  # and really spread
    again = Backoff(initial=0.1, max_delay=1.0, jitter=0.5, rand=random.Random(7).random)
    assert [again.next_delay(a) for a in range(200)] == delays  # pure given its random source


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"initial": 0.0}, "0 < initial <= max_delay"),
    ({"initial": 3.0, "max_delay": 2.0}, "0 < initial <= max_delay"),
    ({"factor": 0.5}, "factor must be >= 1"),
    ({"jitter": 1.0}, r"jitter must be in \[0, 1\)"),
])
def test_backoff_refuses_nonsense(kwargs: dict[str, float], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Backoff(**kwargs)
    with pytest.raises(ValueError, match="attempt must be >= 0"):
        Backoff().next_delay(-1)


# -- a real server process, killed and started again -----------------------------------------


class Serve:
    """``rlbridge serve`` on a fixed port that a test can kill and start again."""

    def __init__(self, cli: Any, port: int, *extra: str, psk: bytes | None = None) -> None:
        self.cli, self.port, self.extra, self.psk = cli, port, extra, psk
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> Serve:
        proc = self.proc = self.cli.popen("serve", "--port", str(self.port), *self.extra)
        security = None if self.psk is None else Psk(key=self.psk)

        def session() -> None:  # ready when a session opens: the loop serves, not just listens
            Bridge.connect("127.0.0.1", self.port, timeout=1.0, reconnect=False,
                           security=security).close()

        wait_until_ok(session, f"a session with rlbridge serve on port {self.port}",
                      timeout=WAIT, between=lambda: assert_running(proc))
        return self

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.kill()  # SIGKILL: no goodbye, the kernel resets the connections
        self.proc.communicate(timeout=WAIT)

    def terminate(self) -> None:
        assert self.proc is not None
        self.proc.terminate()  # SIGTERM: the server says goodbye to every session
        self.proc.communicate(timeout=WAIT)


@pytest.fixture
def serve(cli: Any, free_port: Callable[[], int]) -> Iterator[Serve]:
    server = Serve(cli, free_port()).start()
    yield server
    if server.proc is not None and server.proc.poll() is None:
        server.terminate()


@pytest.fixture
def bridges(serve: Serve) -> Iterator[Callable[..., Bridge]]:
    opened: list[Bridge] = []

    def make(**kwargs: Any) -> Bridge:
        kwargs.setdefault("timeout", 5.0)
        kwargs.setdefault("reconnect", FAST)
        b = Bridge.connect("127.0.0.1", serve.port, **kwargs)
        opened.append(b)
        return b

    yield make
    for b in opened:
        b.close()


def reconnected(*bs: Bridge, at_least: int = 1) -> Callable[[], bool]:
    return lambda: all(b.reconnects >= at_least and b.link_state is LinkState.CONNECTED
                       for b in bs)


def lost(*bs: Bridge) -> Callable[[], bool]:
    return lambda: all(b.link_state is LinkState.LOST for b in bs)


def session_over(b: Bridge) -> Callable[[], bool]:
    """The ended session's receive thread has exited: nothing of that session is handled
    any more, so whatever the link says now stays until the next session."""
    thread = b._conn._thread
    assert thread is not None
    return lambda: not thread.is_alive()


@pytest.mark.parametrize("how", ["kill", "terminate"])
def test_server_restart_mid_stream_resumes_both_ways_on_tcp_and_udp(
        serve: Serve, bridges: Callable[..., Bridge], how: str) -> None:
    a, b = bridges(name="a"), bridges(name="b")
    links: dict[str, tuple[Any, Any]] = {}
    for transport in ("tcp", "udp"):
        for src, dst, name in ((a, b, "ab"), (b, a, "ba")):
            topic = f"/restart/{how}/{name}/{transport}"
            inbox = dst.subscribe(topic, F64, transport=transport, blocking=True,
                                  buffer_size=256)
            links[f"{name}/{transport}"] = (src.publish(topic, F64, transport=transport), inbox)
    for key, (out, inbox) in links.items():
        assert roundtrip(out, inbox, 1.0), f"{key}: no value before the restart"
    channels = {b_: b_.server_stats()["session"]["channels"] for b_ in (a, b)}

    getattr(serve, how)()
    wait_until(lost(a, b), "both bridges to see the link lost", timeout=WAIT)
    assert a.state is ClientState.RECONNECTING
    assert not a.closed
    serve.start()  # same port; nobody tells the bridges
    wait_until(reconnected(a, b), "both bridges to reconnect by themselves", timeout=WAIT)
    for bridge, before in channels.items():  # the same channel ids, directions, on a new server
        after = bridge.server_stats()["session"]["channels"]
        assert {c: d["direction"] for c, d in after.items()} == {
            c: d["direction"] for c, d in before.items()}
    for key, (out, inbox) in links.items():
        assert roundtrip(out, inbox, 2.0), f"{key}: values do not flow after the restart"


def test_values_written_during_the_outage_follow_their_channel_policy(
        serve: Serve, bridges: Callable[..., Bridge]) -> None:
    b = bridges()
    # Subscribed first, so a new session binds it before the publications (bindings are
    # renewed in the order they were made) and it sees what was kept during the outage.
    every = b.subscribe("/outage/every", I32, transport="tcp", blocking=True, buffer_size=64)
    newest = b.subscribe("/outage/newest", I32, transport="udp", blocking=True,
                         buffer_size=64)
    keep = b.publish("/outage/every", I32, transport="tcp", buffer_size=8)
    latest = b.publish("/outage/newest", I32, transport="udp", buffer_size=1)
    keep.write(-1)
    assert every.read(timeout=WAIT) == -1

    serve.kill()
    wait_until(lost(b), "the link lost", timeout=WAIT)
    for i in range(20):
        keep.write(i)
        latest.write(i)
    assert keep.pending() == 8
    assert latest.pending() == 1
    assert keep.statistics().overwritten == 12
    assert latest.statistics().overwritten == 19
    b.send(wait=True)  # does not block while the link is down, keeps the values
    assert keep.pending() == 8

    serve.start()
    wait_until(reconnected(b), "the reconnect", timeout=WAIT)
    assert [every.read(timeout=WAIT) for _ in range(8)] == list(range(12, 20))
    assert newest.read(timeout=WAIT) == 19
    with pytest.raises(TimeoutError):
        every.read(timeout=0.2)
    assert every.lost == 0  # the server numbers from 0 again: not a gap


def test_a_flow_controlled_channel_is_credited_afresh_after_a_reconnect(
        serve: Serve, bridges: Callable[..., Bridge]) -> None:
    """Credit the send thread recorded in the old session (sent or lost with its socket)
    does not carry over: the new binding starts from the ring's size on both sides, so more
    than a ring's worth flows after the reconnect."""
    sub, pub = bridges(name="sub"), bridges(name="pub")
    ring = 64
    inbox = sub.subscribe("/credit/again", I32, transport="tcp", blocking=True,
                          buffer_size=ring)
    out = pub.publish("/credit/again", I32, transport="tcp", buffer_size=ring)
    assert inbox.flow

    def stream(count: int) -> list[int]:
        got: list[int] = []
        reader = threading.Thread(
            target=lambda: got.extend(inbox.read(timeout=WAIT) for _ in range(count)))
        reader.start()
        for i in range(count):
            assert out.wait_writable(timeout=WAIT)
            out.write(i)
        reader.join(2 * WAIT)
        return got

    assert stream(4 * ring) == list(range(4 * ring))
    assert inbox.credited > ring  # credit was granted in this session
    serve.kill()
    wait_until(lost(sub, pub), "the link lost", timeout=WAIT)
    serve.start()
    wait_until(reconnected(sub, pub), "the reconnect", timeout=WAIT)
    assert stream(4 * ring) == list(range(4 * ring))
    assert inbox.lost == 0


@pytest.mark.parametrize("unread", [8, 5])
def test_a_rebind_grants_only_the_free_room_of_a_ring_holding_unread_values(
        serve: Serve, bridges: Callable[..., Bridge], unread: int) -> None:
    """The link drops under a reader that has not read: its unread values stay in the ring,
    so the new binding's first credit is the ring's free room (none when full), not its
    size. What the publisher sends meanwhile waits in the server's backlog; nothing is
    overwritten, and the reader gets every value in order."""
    sub, pub = bridges(name="sub"), bridges(name="pub")
    ring = 8
    inbox = sub.subscribe("/credit/unread", I32, transport="tcp", blocking=True,
                          buffer_size=ring)
    out = pub.publish("/credit/unread", I32, transport="tcp", buffer_size=4 * ring)
    total = unread + 2 * ring
    out.write_many(list(range(unread)))
    wait_until(lambda: len(inbox) == unread, "the values in the reader's ring", timeout=WAIT)
    serve.kill()
    wait_until(lost(sub, pub), "the link lost", timeout=WAIT)
    serve.start()
    wait_until(reconnected(sub, pub), "the reconnect", timeout=WAIT)
    out.write_many(list(range(unread, total)))

    def server_side() -> dict[str, int]:
        channels: dict[str, dict[str, int]] = sub.server_stats()["session"]["channels"]
        return channels[str(inbox.channel_id)]

    wait_until(lambda: server_side()["values_out"] + server_side()["backlog"] == 2 * ring,
               "the new values at the server", timeout=WAIT)
    assert server_side()["credit_limit"] == ring - unread
    assert server_side()["values_out"] == ring - unread  # the free room, no more
    got: list[int] = []
    with contextlib.suppress(TimeoutError):
        while len(got) < total:
            got.append(inbox.read(timeout=WAIT))
    assert got == list(range(total))
    assert inbox.statistics().overwritten == 0
    assert inbox.lost == 0


def test_blocking_reader_waits_across_a_reconnect(serve: Serve,
                                                  bridges: Callable[..., Bridge]) -> None:
    sub, pub = bridges(), bridges()
    inbox = sub.subscribe("/across", F64, transport="tcp", blocking=True)
    out = pub.publish("/across", F64, transport="tcp")
    got: list[object] = []
    reader = threading.Thread(target=lambda: got.append(inbox.read(timeout=60)))
    reader.start()
    serve.kill()
    wait_until(lost(sub, pub), "the link lost", timeout=WAIT)
    serve.start()
    wait_until(reconnected(sub, pub), "the reconnect", timeout=WAIT)
    assert reader.is_alive(), "the blocked reader gave up during the outage"
    wait_until(lambda: out.write(5.0) or not reader.is_alive(),
               "the reader to get a value", timeout=WAIT)
    reader.join(WAIT)
    assert got == [5.0]


def test_close_wakes_a_reader_without_timeout_and_stops_mid_backoff(
        serve: Serve, bridges: Callable[..., Bridge]) -> None:
    b = bridges(reconnect=Backoff(initial=60.0, max_delay=60.0))
    inbox = b.subscribe("/forever", F64, transport="tcp", blocking=True)
    errors: list[BaseException] = []

    def read_forever() -> None:
        try:
            inbox.read()  # no timeout
        except ChannelClosed as exc:
            errors.append(exc)

    reader = threading.Thread(target=read_forever)
    reader.start()
    serve.kill()
    wait_until(lambda: b.state is ClientState.RECONNECTING,
               "the supervisor to back off", timeout=WAIT)
    closer = threading.Thread(target=b.close)
    closer.start()
    closer.join(10.0)  # the backoff is 60 s: only an interrupted wait ends sooner
    assert not closer.is_alive(), "close() waited for the reconnect backoff"
    reader.join(WAIT)
    assert not reader.is_alive()
    assert len(errors) == 1
    assert b.closed
    assert b.state is ClientState.CLOSED
    assert [t.name for t in threading.enumerate() if t.name.startswith("rlbridge-")
            and t.name != "rlbridge-server"] == []


def test_close_aborts_a_handshake_that_gets_no_answer(serve: Serve,
                                                      bridges: Callable[..., Bridge]) -> None:
    b = bridges(timeout=60.0)
    serve.kill()
    wait_until(lost(b), "the link lost", timeout=WAIT)
    with socket.socket() as mute:  # takes the server's port, accepts, never answers
        mute.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        mute.bind(("127.0.0.1", serve.port))
        mute.listen()
        mute.settimeout(WAIT)
        conn, _ = mute.accept()  # the bridge's reconnect attempt is now in its handshake
        with conn:
            closer = threading.Thread(target=b.close)
            closer.start()
            closer.join(10.0)  # the handshake would wait 60 s
            assert not closer.is_alive(), "close() waited for the handshake's timeout"
    assert b.closed


def test_without_reconnect_the_session_end_closes_channels_and_wakes_readers(
        serve: Serve, bridges: Callable[..., Bridge]) -> None:
    b = bridges(reconnect=False)
    inbox = b.subscribe("/once", F64, transport="tcp", blocking=True)
    errors: list[BaseException] = []

    def read_forever() -> None:
        try:
            inbox.read()
        except ChannelClosed as exc:
            errors.append(exc)

    reader = threading.Thread(target=read_forever)
    reader.start()
    serve.terminate()
    reader.join(WAIT)
    assert not reader.is_alive()
    assert len(errors) == 1
    assert b.closed
    assert b.state is ClientState.CLOSED
    assert "server closed the session" in b.close_reason
    assert b.reconnects == 0


# -- link state and fail-safes for control code ----------------------------------------------


def test_link_events_callback_and_property_report_loss_and_return(
        serve: Serve, bridges: Callable[..., Bridge]) -> None:
    b = bridges()
    events = b.link_events()
    seen: list[LinkState] = []
    b.on_link_change(seen.append)
    first = events.read()
    assert isinstance(first, LinkEvent)
    assert first.state is LinkState.CONNECTED
    with pytest.raises(WouldBlock):  # nothing new: a FIFO of events, not a state
        events.try_read()
    assert events.read_many() == []

    serve.kill()
    wait_until(lost(b), "the link lost", timeout=WAIT)
    down = events.read_many()
    assert [e.state for e in down][-1] is LinkState.LOST
    assert "server closed the TCP connection" in down[-1].reason or \
        "connection failed" in down[-1].reason
    assert down[-1].at_ns > first.at_ns
    with pytest.raises(AttributeError):
        down[-1].state = LinkState.CONNECTED  # type: ignore[misc]  # frozen

    serve.start()
    wait_until(reconnected(b), "the reconnect", timeout=WAIT)
    back = events.read_many()
    assert back[-1].state is LinkState.CONNECTED
    assert back[-1].reason.startswith("reconnected: session")
    assert seen[-2:] == [LinkState.LOST, LinkState.CONNECTED]
    b.close()
    final = events.read_many()
    assert final[-1].state is LinkState.LOST
    assert final[-1].reason == "closed by the client"
    with pytest.raises(ChannelClosed):
        events.read()  # the bridge is gone: its event channel says so


@pytest.mark.parametrize("how", ["kill", "terminate"])
def test_fail_safes_hold_safe_value_and_raise_while_the_link_is_lost(
        serve: Serve, bridges: Callable[..., Bridge], how: str) -> None:
    """A kill (no goodbye) and a clean shutdown (SIGTERM: the server's goodbye) alike."""
    sub, pub = bridges(name="sub"), bridges(name="pub")
    hold = sub.subscribe("/fs/hold", F64, transport="udp", initial=0.0)
    safe = sub.subscribe("/fs/safe", F64, transport="udp", initial=0.0,
                         policy=Policy(on_lost=SafeValue(-1.0)))
    strict = sub.subscribe("/fs/raise", F64, transport="udp", blocking=True,
                           policy=Policy(on_lost="raise"))
    outs = [pub.publish(f"/fs/{n}", F64, transport="udp") for n in ("hold", "safe", "raise")]
    for out in outs:
        out.write(3.0)
    wait_until(lambda: hold.read() == 3.0 and safe.read() == 3.0, "the first values", timeout=WAIT)
    assert strict.read(timeout=WAIT) == 3.0

    events = sub.link_events()
    getattr(serve, how)()
    wait_until(lost(sub), "the link lost", timeout=WAIT)
    assert safe.read() == -1.0  # the same source: lost means the fail-safes have engaged
    # The goodbye's session has ended: nothing it still reads may report the link back up.
    wait_until(session_over(sub), "the ended session's receive thread to exit", timeout=WAIT)
    assert sub.link_state is LinkState.LOST
    states = [e.state for e in events.read_many()]
    assert LinkState.LOST in states
    assert set(states[states.index(LinkState.LOST):]) == {LinkState.LOST}  # never back up
    age = hold.age_ns
    assert hold.read() == 3.0
    wait_until(lambda: hold.age_ns > age, "the held value to age", timeout=WAIT)
    assert safe.read() == -1.0
    assert safe.try_read() == -1.0
    with pytest.raises(LinkLost, match="on_lost='raise'"):
        strict.read(timeout=60)  # raises at once: no wait for a value that cannot come

    serve.start()
    wait_until(reconnected(sub, pub), "the reconnect", timeout=WAIT)
    for out in outs:
        out.write(4.0)
    wait_until(lambda: hold.read() == 4.0 and safe.read() == 4.0,
               "values after the reconnect", timeout=WAIT)
    assert strict.read(timeout=WAIT) == 4.0


def test_on_lost_refuses_unknown_policies(serve: Serve, bridges: Callable[..., Bridge]) -> None:
    with pytest.raises(ValueError, match=r"on_lost='zero' must be 'hold', 'raise' or SafeValue"):
        bridges().subscribe("/fs/bad", F64, policy=Policy(on_lost="zero"))  # type: ignore[arg-type]


def test_io_priority_reports_thread_ids_and_follows_a_reconnect(
        serve: Serve, bridges: Callable[..., Bridge]) -> None:
    b = bridges()
    with warnings.catch_warnings(record=True):  # a refusal is one RealTimeWarning
        applied = b.set_io_priority(1)
    if not applied:
        pytest.skip("SCHED_FIFO refused here (needs CAP_SYS_NICE)")
    ids = [t.native_id for t in threading.enumerate()
           if t.name in ("rlbridge-recv", "rlbridge-send", "rlbridge-reconnect")]
    assert len(ids) == 3
    assert all(os.sched_getscheduler(tid) == os.SCHED_FIFO for tid in ids if tid)
    serve.kill()
    serve.start()
    wait_until(reconnected(b), "the reconnect", timeout=WAIT)
    recv = [t.native_id for t in threading.enumerate() if t.name == "rlbridge-recv"]
    assert recv
    assert recv[0] not in ids
    assert os.sched_getscheduler(recv[0]) == os.SCHED_FIFO  # type: ignore[arg-type]


def test_udp_only_session_reconnects_over_udp(serve: Serve,
                                              bridges: Callable[..., Bridge]) -> None:
    """No TCP connection to break: the client's watchdog notices, the hello goes over UDP."""
    b = bridges(tuning=Tuning(control="udp"))
    inbox = b.subscribe("/udp_only", F64, transport="udp", blocking=True, buffer_size=64)
    out = b.publish("/udp_only", F64, transport="udp")
    assert roundtrip(out, inbox, 1.0)
    serve.kill()
    wait_until(lost(b), "the watchdog to declare the link lost", timeout=WAIT)
    serve.start()
    wait_until(reconnected(b), "the reconnect over UDP", timeout=WAIT)
    assert roundtrip(out, inbox, 2.0)


def test_keyed_session_reconnects_with_fresh_keys_and_link(
        cli: Any, free_port: Callable[[], int], tmp_path: Any) -> None:
    """With a pre-shared key the new session runs a new handshake: new nonces, new datagram
    keys (sealed UDP flows again), and the channels read RTT from the new link monitor."""
    key = os.urandom(32)
    key_file = tmp_path / "psk"
    key_file.write_text(key.hex())
    key_file.chmod(0o600)
    server = Serve(cli, free_port(), "--psk-file", str(key_file), psk=key).start()
    b = Bridge.connect("127.0.0.1", server.port, security=Psk(key=key), reconnect=FAST, timeout=5.0)
    try:
        inbox = b.subscribe("/keyed", F64, transport="udp", blocking=True, buffer_size=64)
        out = b.publish("/keyed", F64, transport="udp")
        assert roundtrip(out, inbox, 1.0)
        first_link = b._conn.link
        server.kill()
        wait_until(lost(b), "the link lost", timeout=WAIT)
        server.start()
        wait_until(reconnected(b), "the keyed reconnect", timeout=WAIT)
        assert roundtrip(out, inbox, 2.0)
        assert b._conn.link is not first_link
        assert inbox._link is b._conn.link
        assert out._link is b._conn.link
    finally:
        b.close()
        server.terminate()
