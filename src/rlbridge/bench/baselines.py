"""Baselines measured in the same run as rlbridge: a raw UDP socket pair, ZeroMQ and Zenoh.

Each baseline is a sender and a receiver process moving 8-byte messages over loopback, one hop,
the best a Python program can do with that transport: the raw socket loop is the floor of any
Python UDP protocol's per-datagram cost, ZeroMQ and Zenoh are what a user would otherwise pick.
Two modes share the roles: ``flood`` (as fast as possible, the receiver counts) for throughput,
and ``paced`` (``time.time_ns()`` at a fixed rate, the receiver records one-way latency).

ZeroMQ and Zenoh are optional (extra ``compare``); without them their rows say
``skipped: <reason>``. Both are publish/subscribe with slow joiners, so their senders send
1-byte warm-up messages until the receiver reports it ``joined``; only 8-byte messages count.
"""

from __future__ import annotations

import functools
import socket
import struct
import time
from typing import Any

from rlbridge.bench.common import (
    Control,
    Params,
    ProcessGroup,
    Role,
    Side,
    Skipped,
    Tally,
    Worker,
    emit,
    flood,
    hold,
    paced,
    wait_for_go,
)

MODULE = "rlbridge.bench.baselines"
STAMP = struct.Struct("<q")
PAYLOAD = b"\0" * 8
WARMUP = b"w"
KINDS = ("udp", "zmq", "zenoh")


def unavailable(kind: str) -> str | None:
    """Why the ``kind`` baseline cannot run here, or None."""
    module = {"zmq": "zmq", "zenoh": "zenoh"}.get(kind)
    if module is None:
        return None
    try:
        __import__(module)
    except ImportError as exc:
        return f"{'pyzmq' if kind == 'zmq' else 'eclipse-zenoh'} not importable ({exc}); " \
               "install the 'compare' extra"
    return None


def _send_loop(control: Control, params: Params, send_payload: Any, send_bytes: Any,
               warmup: Any = None) -> None:
    """Sender body shared by the baselines: ready, warm up until go, send, report, hold."""
    emit("ready")
    wait_for_go(control, warmup)
    if params["mode"] == "flood":
        sent, t0, t1 = flood(send_payload, int(params["count"]), float(params["seconds"]))
    else:
        sent, t0, t1 = paced(lambda ns: send_bytes(STAMP.pack(ns)), float(params["rate_hz"]),
                             int(params["count"]))
    emit("sent", sent=sent, t_start=t0, t_end=t1)
    hold(control)


def _record(tally: Tally, data: bytes, now: float, latency: bool) -> None:
    """Count one received message (warm-ups are not counted); keep its latency if paced."""
    if len(data) != 8:
        return
    if latency:
        tally.samples.append(time.time_ns() - STAMP.unpack(data)[0])
    tally.add(1, now)


# -- raw UDP -------------------------------------------------------------------------------
def udp_recv(params: Params) -> None:
    """One blocking ``recv`` per datagram; a kernel receive timeout (no poll) checks the end."""
    control = Control()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, struct.pack("ll", 0, 50_000))
    sock.bind((params["host"], 0))
    emit("ready", port=sock.getsockname()[1])
    emit("joined")
    tally = Tally(control, float(params["idle_s"]))
    _drain(tally, functools.partial(sock.recv, 64), BlockingIOError, params["mode"] == "paced")
    tally.report()


def _drain(tally: Tally, recv: Any, timed_out: type[BaseException], latency: bool) -> None:
    """Receive until the tally says done; ``recv()`` raises ``timed_out`` after a silence."""
    mono = time.monotonic
    while not tally.done(mono()):
        n, last = 0, 0.0
        try:
            while True:
                data = recv()
                last = mono()
                if latency:
                    _record(tally, data, last, True)
                elif len(data) == 8:
                    n += 1
        except timed_out:
            pass
        tally.add(n, last)


def udp_send(params: Params) -> None:
    control = Control()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    addr = (params["host"], int(params["port"]))
    _send_loop(control, params, functools.partial(sock.sendto, PAYLOAD, addr),
               lambda b: sock.sendto(b, addr))


# -- ZeroMQ --------------------------------------------------------------------------------
def zmq_sub(params: Params) -> None:
    """SUB binds on side a (the listener), with a receive timeout to check the stop rule."""
    import zmq

    control = Control()
    ctx = zmq.Context()
    sock = ctx.socket(zmq.SUB)
    sock.setsockopt(zmq.SUBSCRIBE, b"")
    sock.setsockopt(zmq.RCVTIMEO, 50)
    port = sock.bind_to_random_port(f"tcp://{params['host']}")
    emit("ready", port=port)
    tally = Tally(control, float(params["idle_s"]))
    while True:
        try:
            if sock.recv() == WARMUP:
                break
        except zmq.Again:
            pass
    emit("joined")
    _drain(tally, sock.recv, zmq.Again, params["mode"] == "paced")
    tally.report()
    sock.close(0)
    ctx.term()


def zmq_pub(params: Params) -> None:
    """PUB connects; default high-water mark (1000): past it ZeroMQ drops, the count shows it."""
    import zmq

    control = Control()
    ctx = zmq.Context()
    sock = ctx.socket(zmq.PUB)
    sock.connect(f"tcp://{params['host']}:{params['port']}")
    _send_loop(control, params, functools.partial(sock.send, PAYLOAD), sock.send,
               functools.partial(sock.send, WARMUP))


# -- Zenoh ---------------------------------------------------------------------------------
def _zenoh_session(listen: str | None, connect: str | None) -> Any:
    """Peer mode, no multicast scouting, explicit TCP endpoints (listen here or connect there)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", f'["{listen}"]' if listen else "[]")
    conf.insert_json5("connect/endpoints", f'["{connect}"]' if connect else "[]")
    return zenoh.open(conf)


def zenoh_sub(params: Params) -> None:
    """Listens on ``tcp/<host>:<port>`` (port picked by the parent); counts in the callback."""
    control = Control()
    session = _zenoh_session(f"tcp/{params['host']}:{params['port']}", None)
    tally = Tally(control, float(params["idle_s"]))
    latency = params["mode"] == "paced"
    joined = [False]

    def on_warmup(_sample: Any) -> None:
        if not joined[0]:
            joined[0] = True
            emit("joined")

    def on_data(sample: Any) -> None:
        now = time.monotonic()
        if latency:
            _record(tally, sample.payload.to_bytes(), now, True)
        else:
            tally.add(1, now)

    subs = [session.declare_subscriber("bench/warmup", on_warmup),
            session.declare_subscriber("bench/data", on_data)]
    emit("ready", port=params["port"])
    while not tally.done(time.monotonic()):
        time.sleep(0.02)
    tally.report()
    for sub in subs:
        sub.undeclare()
    session.close()


def zenoh_pub(params: Params) -> None:
    control = Control()
    session = _zenoh_session(None, f"tcp/{params['host']}:{params['port']}")
    pub = session.declare_publisher("bench/data")
    warm = session.declare_publisher("bench/warmup")
    _send_loop(control, params, functools.partial(pub.put, PAYLOAD), pub.put,
               functools.partial(warm.put, WARMUP))


ROLES: dict[str, Role] = {
    "udp_recv": udp_recv, "udp_send": udp_send,
    "zmq_sub": zmq_sub, "zmq_pub": zmq_pub,
    "zenoh_sub": zenoh_sub, "zenoh_pub": zenoh_pub,
}
_ROLE_NAMES = {"udp": ("udp_recv", "udp_send"), "zmq": ("zmq_sub", "zmq_pub"),
               "zenoh": ("zenoh_sub", "zenoh_pub")}


#: Zenoh's listen port where ``host`` is not an address of this namespace (an emulated
#: link's fresh namespace, where every port is free).
ZENOH_NAMESPACE_PORT = 17447


def free_port(host: str) -> int:
    """A TCP port that was free a moment ago (Zenoh wants its listen port up front)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, 0))
        except OSError:  # EADDRNOTAVAIL: host lives in another (fresh) namespace
            return ZENOH_NAMESPACE_PORT
        port: int = s.getsockname()[1]
        return port


def spawn_pair(group: ProcessGroup, kind: str, mode: Params,
               rx_side: Side = "a") -> tuple[Worker, Worker]:
    """Receiver on ``rx_side`` (default a), sender on the other side, for baseline ``kind``.

    Raises Skipped if the package is missing. ``mode`` holds ``mode`` (``flood`` or
    ``paced``) and its knobs (``count``, ``seconds``, ``rate_hz``, ``idle_s``).
    """
    reason = unavailable(kind)
    if reason is not None:
        raise Skipped(reason)
    rx_role, tx_role = _ROLE_NAMES[kind]
    tx_side: Side = "b" if rx_side == "a" else "a"
    host = group.link.address(rx_side)
    rx_params: Params = {"host": host, **mode}
    if kind == "zenoh":
        rx_params["port"] = free_port(host)
    rx, ready = group.spawn("receiver", rx_side, MODULE, rx_role, rx_params)
    tx, _ = group.spawn("sender", tx_side, MODULE, tx_role,
                        {"host": host, "port": ready["port"], **mode})
    return tx, rx
