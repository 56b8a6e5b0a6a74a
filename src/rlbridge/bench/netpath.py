"""One stream across a (possibly emulated) network: middleware <-> bridge server <-> SDK client.

The thesis measured the bridge as deployed (figure 3.4, appendix A): the middleware publisher
and the bridge server on one machine, the control application on another, the network in
between. Here side ``"a"`` of a :class:`~rlbridge.bench.common.Link` runs one process holding
the bridge server *and* an in-process bus with the middleware-side endpoint; side ``"b"`` runs
the SDK client. With :class:`~rlbridge.netem.EmulatedLink` the sides are two network namespaces
joined by the delaying, dropping relay; both still read one host clock, so one-way latency is
exact, not half a round trip.

* ``down`` (thesis points A to D): the bus publisher publishes ``time.time_ns()`` at a fixed
  rate; the client reads a *blocking* channel and stamps the moment ``read`` returns it.
* ``up`` (points E to H, figure 4.4): the client writes ``time.time_ns()`` into an outgoing
  channel (optionally through the SDK's send loop, ``send_rate_hz``); the bus subscriber's
  callback stamps the moment the value is published on the middleware side.

Every value carries its send stamp, which is unique, so the parent maps each received value
back to its sequence number: a value that never arrives is counted lost, never dropped from the
statistics silently. Channel policies (``latest``, ``redundancy``, ``max_age_ms``) are passed
through as keyword arguments only when the parent asked for them (see ``bench/policies.py``).
"""

from __future__ import annotations

import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from rlbridge.bench.common import (
    STARTUP_S,
    BenchError,
    Control,
    Link,
    Params,
    ProcessGroup,
    Role,
    Side,
    emit,
    hold,
    paced,
    wait_for_go,
)

MODULE = "rlbridge.bench.netpath"
MSG_TYPE = "std_msgs/msg/Int64"
TOPICS = {"down": "/eval/down", "up": "/eval/up"}
#: Silence after the last expected value before the receiver gives up on the rest (lost).
IDLE_S = 1.5


@dataclass(frozen=True)
class StreamSpec:
    """One measured stream: direction, transport, rate, length, and the client's options."""

    direction: str = "down"
    transport: str = "udp"
    nodelay: bool = False
    rate_hz: float = 100.0
    count: int = 1000
    send_rate_hz: float | None = None
    #: ``Policy`` options of the client's subscribe/publish (only those this build has).
    policy: dict[str, Any] = field(default_factory=dict)
    #: Read incoming values with ``read_with_age`` and count those older than this (ms).
    age_limit_ms: float | None = None

    def __post_init__(self) -> None:
        if self.direction not in TOPICS:
            raise ValueError(f"direction must be 'down' or 'up', got {self.direction!r}")
        if self.transport not in ("tcp", "udp"):
            raise ValueError(f"transport must be 'tcp' or 'udp', got {self.transport!r}")
        if self.rate_hz <= 0 or self.count < 1:
            raise ValueError("rate_hz must be > 0 and count >= 1")


@dataclass
class StreamResult:
    """Per-sample outcome: ``recv_ns[i]`` is None for a lost value ``i``."""

    spec: StreamSpec
    sent_ns: list[int]
    recv_ns: list[int | None]
    t_start: float
    t_end: float
    duplicates: int = 0
    flagged_old: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def latencies_ms(self) -> list[float | None]:
        return [None if r is None else (r - s) / 1e6 for s, r in zip(self.sent_ns, self.recv_ns,
                                                                     strict=True)]

    @property
    def lost(self) -> int:
        return sum(r is None for r in self.recv_ns)

    @property
    def send_rate(self) -> float:
        span = self.t_end - self.t_start
        return len(self.sent_ns) / span if span > 0 else float("nan")

    def csv_rows(self) -> list[str]:
        """``seq,sent_ns,recv_ns,latency_ms`` lines (recv and latency empty when lost)."""
        rows = ["seq,sent_ns,recv_ns,latency_ms"]
        for i, (s, r) in enumerate(zip(self.sent_ns, self.recv_ns, strict=True)):
            rows.append(f"{i},{s},," if r is None else f"{i},{s},{r},{(r - s) / 1e6:.4f}")
        return rows


class PriorityLink:
    """A link whose processes run ``SCHED_FIFO`` at ``priority`` (``chrt -f``), both sides.

    On a shared machine a measured process that waits for a CPU looks exactly like a slow
    network: a 100 Hz stream then shows ramps of samples delivered late in a burst. Running
    every measured process (bridge, client, baselines alike) at a real-time priority below the
    relay's keeps other load out of the figures; they sleep between samples, so they cost the
    machine little. Not for flood benchmarks (a busy FIFO process starves the others).
    """

    def __init__(self, link: Link, priority: int) -> None:
        if not 1 <= priority <= 99:
            raise ValueError(f"priority must be in [1, 99], got {priority}")
        self.link = link
        self.priority = priority
        self.name = f"{link.name} (SCHED_FIFO {priority})"

    def address(self, side: Side) -> str:
        return self.link.address(side)

    def popen(self, side: Side, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[bytes]:
        return self.link.popen(side, ["chrt", "-f", str(self.priority), *argv], **kwargs)


# -- side a: bridge server + middleware endpoint (one process) -------------------------------
def bridge_side(params: Params) -> None:
    """Server with an in-process bus; publishes (down) or records (up) on the bus directly."""
    from rlbridge.adapters.base import QoS
    from rlbridge.adapters.inproc import InProcessBus
    from rlbridge.server import ServerConfig
    from rlbridge.server.app import ServerThread

    control = Control()
    bus = InProcessBus()
    server = ServerThread(ServerConfig(host=params["host"], port=0, insecure=True,  # netns
                                       nodelay=bool(params["nodelay"])), adapter=bus).start()
    direction = params["direction"]
    if direction == "down":
        pub = bus.create_publisher(TOPICS["down"], MSG_TYPE, "data", QoS())
        emit("ready", port=server.port)
        wait_for_go(control)
        stamps: list[int] = []

        def publish(ns: int) -> None:
            stamps.append(ns)
            pub.publish([ns])

        _, t0, t1 = paced(publish, float(params["rate_hz"]), int(params["count"]))
        emit("sent", sent=len(stamps), stamps=stamps, t_start=t0, t_end=t1)
        hold(control)
    else:
        got: list[tuple[int, int]] = []
        lock = threading.Lock()

        def on_values(values: Any) -> None:
            now = time.time_ns()
            with lock:
                got.extend((int(v), now) for v in values)

        bus.subscribe(TOPICS["up"], MSG_TYPE, "data", QoS(), on_values)
        emit("ready", port=server.port)
        _await_values(control, lambda: len(got))
        with lock:
            emit("result", values=got)
        hold(control)


def _await_values(control: Control, count: Callable[[], int]) -> None:
    """Wait for ``expect``, then until that many values arrived or ``IDLE_S`` of silence."""
    expected = int(control.wait("expect", 1e6)["count"])
    last_n, last_t = -1, time.monotonic()
    while True:
        n = count()
        now = time.monotonic()
        if n >= expected:
            return
        if n != last_n:
            last_n, last_t = n, now
        elif now - last_t > IDLE_S:
            return
        time.sleep(0.02)


# -- side b: the SDK client --------------------------------------------------------------------
def client_side(params: Params) -> None:
    """The control application: a blocking incoming channel (down) or a paced writer (up)."""
    from rlbridge.csp.bridge import Bridge
    from rlbridge.csp.options import Policy

    control = Control()
    send_rate = params.get("send_rate_hz")
    bridge = Bridge.connect(params["host"], int(params["port"]), nodelay=bool(params["nodelay"]),
                            name="eval-client", send_rate_hz=send_rate)
    policy: Params = params.get("policy", {})
    if params["direction"] == "up":
        out = bridge.publish(TOPICS["up"], MSG_TYPE, "data", transport=params["transport"],
                             through_buffer=send_rate is not None, policy=Policy(**policy))
        emit("ready")
        wait_for_go(control)
        stamps: list[int] = []

        def write(ns: int) -> None:
            stamps.append(ns)
            out.write(ns)

        _, t0, t1 = paced(write, float(params["rate_hz"]), int(params["count"]))
        emit("sent", sent=len(stamps), stamps=stamps, t_start=t0, t_end=t1)
        hold(control)
        return
    ch = bridge.subscribe(TOPICS["down"], MSG_TYPE, "data", transport=params["transport"],
                          blocking=True, buffer_size=4096, policy=Policy(**policy))
    emit("ready")
    age_limit = params.get("age_limit_ms")
    read: Callable[[float], Any] = ch.read_with_age if age_limit is not None else ch.read
    got: list[tuple[int, int]] = []
    flagged = 0
    stop = threading.Event()

    def reader() -> None:
        nonlocal flagged
        while not stop.is_set():
            try:
                item = read(0.05)
            except TimeoutError:
                continue
            now = time.time_ns()
            if age_limit is not None:
                item, age_ns = item  # read_with_age -> AgedValue(value, age_ns)
                flagged += age_ns > float(age_limit) * 1e6
            got.append((int(item), now))

    thread = threading.Thread(target=reader, name="eval-reader", daemon=True)
    thread.start()
    _await_values(control, lambda: len(got))
    stop.set()
    thread.join(5.0)
    extra: Params = {"sdk_lost": ch.lost, "sdk_duplicates": ch.duplicates}
    health = getattr(ch, "health", None)
    if callable(health):
        extra["health"] = repr(health())
    emit("result", values=got, flagged=flagged, extra=extra)
    hold(control)


ROLES: dict[str, Role] = {"bridge_side": bridge_side, "client_side": client_side}


# -- parent --------------------------------------------------------------------------------
def _match(spec: StreamSpec, sent: Params, received: Params) -> StreamResult:
    stamps: list[int] = sent["stamps"]
    index = {s: i for i, s in enumerate(stamps)}
    recv: list[int | None] = [None] * len(stamps)
    duplicates = 0
    for value, at in received["values"]:
        i = index.get(value)
        if i is None:
            raise BenchError(f"received a value that was never sent: {value}")
        if recv[i] is not None:
            duplicates += 1
            continue
        recv[i] = at
    return StreamResult(spec, stamps, recv, float(sent["t_start"]), float(sent["t_end"]),
                        duplicates=duplicates, flagged_old=int(received.get("flagged", 0)),
                        extra=dict(received.get("extra", {})))


def measure_stream(link: Link, spec: StreamSpec) -> StreamResult:
    """One run of ``spec`` over ``link`` in fresh processes (server side ``a``, client ``b``)."""
    timeout = spec.count / spec.rate_hz + 60.0
    common: Params = {"direction": spec.direction, "rate_hz": spec.rate_hz, "count": spec.count}
    with ProcessGroup(link, lifetime_s=timeout + 120) as group:
        try:
            host = link.address("a")
            server, ready = group.spawn("bridge", "a", MODULE, "bridge_side",
                                        {"host": host, "nodelay": spec.nodelay, **common})
            client, _ = group.spawn("client", "b", MODULE, "client_side", {
                "host": host, "port": ready["port"], "transport": spec.transport,
                "nodelay": spec.nodelay, "send_rate_hz": spec.send_rate_hz,
                "policy": spec.policy, "age_limit_ms": spec.age_limit_ms, **common})
            sender, receiver = (server, client) if spec.direction == "down" else (client, server)
            sender.send("go")
            sent = sender.expect("sent", timeout)
            receiver.send("expect", count=int(sent["sent"]))
            received = receiver.expect("result", timeout + STARTUP_S)
        except BenchError as exc:
            raise BenchError(f"{exc}{group.diagnostics()}") from None
    return _match(spec, sent, received)
