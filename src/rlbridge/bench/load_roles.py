"""The child processes of ``rlbridge bench load`` and ``soak``: many clients, one slow consumer.

A *clients* process hosts several SDK sessions (``Bridge``), each with ``channels`` outgoing
channels published at ``rate_hz`` and the same topics subscribed back, so every value makes the
deployed round trip: SDK -> server -> in-process bus -> server -> SDK. One ticker thread per
process writes ``time.time()`` on every outgoing channel on an absolute schedule; when it falls
behind it writes the late ticks at once up to ``catch_up_s`` behind, and skips (counts) the
rest instead of bursting for longer, so the offered load is what it says.

Latency is measured on channel 0 of every session: a thread per session blocks on that channel
and records ``time.time() - value`` when a value becomes readable. The other channels are
non-blocking latest-value channels (what a control loop reads) whose delivered values are
counted from their ring's ``written`` counter, without a reader paying per value.

The *slow* process is a raw protocol client (the wire codec on a plain socket, no SDK): it
subscribes over TCP with a tiny receive buffer, reads the acks, then never reads again, so the
server's queue to it fills and the server must drop, and count, what does not fit.

The parent switches measurement phases (``phase`` commands); each process reports per-session
counters and latency percentiles per phase at the end.
"""

from __future__ import annotations

import contextlib
import os
import socket
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from rlbridge.bench.common import Control, Params, Role, emit, hold
from rlbridge.bench.load_book import F64, Book, topic
from rlbridge.bench.load_raw import RawSessions
from rlbridge.cli.options import tuning_of
from rlbridge.wire import PacketCodec

BULK_TOPIC = "/load/bulk"
#: Session writes due closer together than this go out back to back (see ``tick_loop``).
SLOT_S = 0.001


class _SdkSession(Book):
    """One SDK session: ``channels`` publishers and their subscriptions, and a probe thread."""

    def __init__(self, params: Params, index: int, phase: list[str]) -> None:
        from rlbridge.client.bridge import Bridge

        super().__init__(index, phase)
        transport = params["transport"]
        # Tuning's switch_interval=None: a hundred SDK threads in one process hand the GIL over at
        # CPython's default pace; the shortened interval the SDK sets for HRT loops thrashes.
        self.bridge = Bridge.connect(params["host"], int(params["port"]), name=f"load-{index}",
                                     timeout=30.0,
                                     tuning=tuning_of(bundles=bool(params.get("bundles", True))))
        n = int(params["channels"])
        self.subs = [self.bridge.subscribe(topic(index, c), F64, transport=transport,
                                           blocking=c == 0, buffer_size=64 if c == 0 else 1)
                     for c in range(n)]
        self.pubs = [self.bridge.publish(topic(index, c), F64, transport=transport,
                                         through_buffer=True, buffer_size=16)
                     for c in range(n)]
        self._running = True
        self._probe = threading.Thread(target=self._read_probe, name=f"probe-{index}",
                                       daemon=True)
        self._probe.start()

    def received(self) -> int:
        return sum(ch.statistics().written for ch in self.subs)

    def extra(self) -> Params:
        self._running = False
        return {"lost_seq": sum(ch.lost for ch in self.subs),
                "overwritten": sum(ch.statistics().overwritten for ch in self.pubs)}

    def _read_probe(self) -> None:
        probe, now = self.subs[0], time.time
        while self._running:
            try:
                value = probe.read(0.2)
            except TimeoutError:
                continue
            except Exception:  # the session closed under us: stop measuring, report the rest
                return
            self.record((now() - value) * 1e6)

    def write_all(self, stamp: float) -> None:
        for ch in self.pubs:
            ch.write(stamp)
        self.bridge.send()  # one hand-off to the send thread per tick, as a control loop does
        self.sent += len(self.pubs)

    def close(self) -> None:
        self._running = False
        self.bridge.close()


class _Sessions(Protocol):
    def write_all(self, stamp: float) -> None: ...
    def received(self) -> int: ...
    def mark(self, phase: str) -> None: ...
    def result(self) -> Params: ...
    def close(self) -> None: ...


def tick_loop(params: Params, sessions: Sequence[_Sessions], phase: list[str],
              wait_until: Callable[[float], None]) -> None:
    """The shared ticker: go, phases, stop (or ``max_s``), drain, report, hold."""
    control = Control()
    emit("ready")
    control.wait("go", float(params["max_s"]))
    for s in sessions:
        s.mark("warmup")
    # Sessions are staggered over the period, as independent clients would be: session j of
    # n writes at j/n of each period, so the server sees a steady stream, not a burst per tick.
    # Writes due within SLOT_S of each other go out without a wait between them (the process
    # wakes at most ~1,000 times a second, not once per session write), and the sockets are
    # read at least once per round. A process the machine did not schedule in time writes its
    # late ticks at once, as a preempted control loop would, up to ``catch_up_s`` behind;
    # further behind it skips them (counted), so a starved generator does not burst for long.
    n = len(sessions)
    step = 1.0 / float(params["rate_hz"]) / n
    catch_up = max(float(params.get("catch_up_s", 0.1)), step * n)
    start = time.monotonic()
    end = start + float(params["max_s"])
    k = skipped = 0
    while True:
        now = time.monotonic()
        if now >= end or control.poll("stop") is not None:
            break
        if k % n == 0:
            msg = control.poll("phase")
            if msg is not None:
                phase[0] = str(msg["name"])
                for s in sessions:
                    s.mark(phase[0])
        sessions[k % n].write_all(time.time())
        k += 1
        due = start + k * step
        now = time.monotonic()
        if now > due + catch_up:  # too far behind: skip, do not burst
            late = int((now - due) / step)
            skipped += late
            k += late
            due = start + k * step
        if k % n == 0 or due - now > SLOT_S:
            wait_until(due)
    for s in sessions:
        s.mark("drain")  # the last phase ends here; in-flight values count in the totals only
    drain(sessions, wait_until, float(params["drain_s"]))
    emit("result", sessions=[s.result() for s in sessions], writes=k, skipped=skipped)
    for s in sessions:
        s.close()
    hold(control)


def drain(sessions: Sequence[_Sessions], wait_until: Callable[[float], None],
          limit_s: float, quiet_s: float = 2.0) -> None:
    """Read until nothing has arrived for ``quiet_s`` (at most ``limit_s``).

    An overloaded server holds seconds of values in its receive buffer when the clients stop;
    they are late, not lost, and the totals should say so. What is still missing after a
    quiet ``quiet_s`` (or at the limit) is reported as in flight or lost.
    """
    end = time.monotonic() + limit_s
    last, quiet_since = -1, time.monotonic()
    while (now := time.monotonic()) < end and now - quiet_since < quiet_s:
        wait_until(min(end, now + 0.25))
        got = sum(s.received() for s in sessions)
        if got != last:
            last, quiet_since = got, time.monotonic()


def _yield_cpu(params: Params) -> None:
    """Lower this process's priority by ``params["nice"]`` (a load generator, not the product)."""
    if int(params.get("nice", 0)):
        os.nice(int(params["nice"]))


def clients(params: Params) -> None:
    """SDK sessions ``params["ids"]`` in this process (``Bridge``, its threads, its channels)."""
    _yield_cpu(params)
    phase = ["warmup"]
    sessions = [_SdkSession(params, i, phase) for i in params["ids"]]
    tick_loop(params, sessions, phase, lambda due: time.sleep(max(0.0, due - time.monotonic())))


def _tcp_session(params: Params, name: str, requests: list[Any],
                 rcvbuf: int | None = None) -> socket.socket:
    """A raw TCP session with ``requests`` (TopicConnects) acknowledged; raises on a refusal."""
    from rlbridge.wire import PROTOCOL_VERSION, FrameDecoder, Hello, TopicAck, TopicError

    codec = PacketCodec()
    sock = socket.socket()
    if rcvbuf is not None:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.connect((params["host"], int(params["port"])))
    sock.settimeout(30)
    out = bytearray()
    codec.encode_frame_into(Hello(PROTOCOL_VERSION, name), out)
    for request in requests:
        codec.encode_frame_into(request, out)
    sock.sendall(out)
    decoder = FrameDecoder(codec)
    acked = 0
    while acked < len(requests):
        for packet in decoder.feed(sock.recv(4096)):
            if isinstance(packet, TopicError):
                raise RuntimeError(f"{name}: {packet.reason}")
            acked += isinstance(packet, TopicAck)
    return sock


def _discard(sock: socket.socket) -> None:
    with contextlib.suppress(OSError):
        while sock.recv(1 << 20):
            pass


def slow(params: Params) -> None:
    """Subscribe over TCP, read the acks, then never read again (``stall`` false: read all).

    The consumer subscribes to ``params["topics"]`` (the clients' topics) and to a bulk topic
    that a second session of this process feeds with ``bulk_rate`` values/s in batches, so
    that its queue fills within seconds whatever rate the clients' topics reach here.
    """
    from rlbridge.wire import Batch, Heartbeat, TopicConnect

    control = Control()
    subs = [TopicConnect(ch, "subscribe", name, F64, transport="tcp")
            for ch, name in enumerate([BULK_TOPIC, *params["topics"]], start=1)]
    stall = bool(params.get("stall", True))
    stalled = _tcp_session(params, "slow-consumer" if stall else "reading-consumer", subs,
                           rcvbuf=4096 if stall else None)
    if not stall:  # the control: the same subscriptions, read as fast as they come
        threading.Thread(target=_discard, args=(stalled,), daemon=True).start()
    feeder = _tcp_session(params, "bulk-feeder",
                          [TopicConnect(1, "publish", BULK_TOPIC, F64, transport="tcp")])
    emit("ready", channels=len(subs))
    codec, hz, n = PacketCodec(), 20.0, max(1, int(params["bulk_rate"] / 20))
    values, seq = [1.0] * n, 0
    start = time.monotonic()
    end = start + float(params["max_s"])
    while time.monotonic() < end:  # ends earlier when the parent closes stdin (Control)
        feeder.sendall(codec.encode_frame(Batch(1, seq, [time.time_ns()] * n, values)))
        # A stalled reader is still alive: it writes heartbeats, so the watchdog keeps it.
        stalled.sendall(codec.encode_frame(Heartbeat(time.monotonic_ns())))
        seq += n
        time.sleep(max(0.0, start + seq / n / hz - time.monotonic()))
    hold(control)
    stalled.close()
    feeder.close()


def raw_clients(params: Params) -> None:
    """Protocol-level sessions (``load_raw``): one thread drives them all."""
    _yield_cpu(params)
    phase = ["warmup"]
    raw = RawSessions(params, phase)
    tick_loop(params, raw.sessions, phase, raw.wait_until)


ROLES: dict[str, Role] = {"clients": clients, "raw": raw_clients, "slow": slow}

