"""The server's inlined value path against the general path it copies (any input, same state).

Two fast paths run once per value on a busy server: ``Inbound.on_value`` (``_admit`` for one
value, with the sequence tracker's and the jitter estimate's steps written out) and
``values_in.bundle`` (``value_packet``'s common case, without the call). Each is driven here
with any program of packets next to its general path, on real bindings of a real session over
the in-process bus, and everything observable must agree: what reached the topic's
subscribers, what the client was told, and every counter. The wall clock is held still during
an example, so the two paths read the same time (the general path reads it per value, the
bundle once per datagram: in a datagram that is the same instant).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rlbridge.adapters.base import QoS
from rlbridge.adapters.inproc import InProcessBus
from rlbridge.server import values_in
from rlbridge.server.admission import ValuesRefused
from rlbridge.server.bindings import Inbound, Outbound
from rlbridge.server.config import ServerConfig
from rlbridge.server.connect import bind
from rlbridge.server.context import ServerContext
from rlbridge.server.handoff import LoopHandoff
from rlbridge.server.session import Session
from rlbridge.wire import Batch, Bundle, Packet, PacketCodec, TopicConnect, Value

PROPS = settings(deadline=None, max_examples=150, suppress_health_check=[HealthCheck.too_slow])
F64 = "std_msgs/msg/Float64"
NOW = 1_700_000_000_000_000_000
#: Channels 1..3 are bound for publishing; 9 is not (its values are refused and answered).
BOUND = (1, 2, 3)

#: A value of the channel's type, one that converts (an int), or one it refuses.
values = st.one_of(st.floats(allow_nan=False, width=64), st.integers(-5, 5),
                   st.sampled_from(["text", None]))
#: Stamps around the held clock: fresh, a little old, far too old for ``max_age_ms``.
stamps = st.integers(NOW - 3_000_000_000, NOW + 1_000_000)


@st.composite
def value_parts(draw: st.DrawFn) -> Value | Batch:
    channel = draw(st.sampled_from((*BOUND, 9)))
    seq = draw(st.integers(0, 12))
    if draw(st.integers(0, 3)):  # mostly single values, as a send round makes them
        return Value(channel, seq, draw(stamps), draw(values))
    vals = draw(st.lists(values, min_size=1, max_size=3))
    return Batch(channel, seq, [draw(stamps) for _ in vals], vals)


class Told:
    """The client's side of the session's answers (a packet sink that keeps them)."""

    def __init__(self) -> None:
        self.packets: list[Packet] = []

    def send(self, packet: Packet, *, data: bool = False) -> bool:
        self.packets.append(packet)
        return True

    def dropped(self) -> int:
        return 0

    def congested(self) -> bool:
        return False


@contextmanager
def wall_clock_at(now: int) -> Iterator[None]:
    """``time.time_ns`` held at ``now`` (both paths read it; nothing else runs meanwhile)."""
    real = time.time_ns
    time.time_ns = lambda: now
    try:
        yield
    finally:
        time.time_ns = real


class Side:
    """A real session with real publish bindings on an in-process bus, and what came out."""

    def __init__(self, max_age_ms: int, latest: bool, offset_ns: int) -> None:
        self.loop = asyncio.new_event_loop()
        self.bus = InProcessBus()
        ctx = ServerContext(ServerConfig(port=0), self.bus, PacketCodec(), self.loop,
                            LoopHandoff(self.loop))
        self.session = Session(ctx, 1, 0x1234, "parity", lambda _s: None)
        self.session.link.clock.offset_ns = offset_ns
        self.published: dict[int, list[Any]] = {}
        self.told = Told()
        for ch in BOUND:
            req = TopicConnect(ch, "publish", f"/parity/c{ch}", F64, transport="udp",
                               max_age_ms=max_age_ms, latest=latest)
            binding = bind(self.session, req)
            assert isinstance(binding, Inbound)
            self.session.inbound[ch] = binding
            got = self.published.setdefault(ch, [])
            self.bus.subscribe(f"/parity/c{ch}", F64, "data", QoS(), got.extend)

    def close(self) -> None:
        self.bus.close()
        self.loop.close()

    def state(self) -> dict[str, Any]:
        s = self.session
        return {
            "published": self.published,
            "told": self.told.packets,
            "retired": dict(s.totals.retired),
            "counters": dict(s.ctx.counters),
            "errors_sent": s.errors_sent,
            "bindings": {ch: binding_state(b) for ch, b in s.inbound.items()},
        }


def binding_state(b: Inbound) -> dict[str, Any]:
    t, j = b.tracker, b.jitter
    return {"tracker": (t.highest, t.accepted, t.lost, t.duplicates, t.stale),
            "jitter": (j.last_transit, j.jitter_ns), "one_way_ns": b.one_way_ns,
            "values_in": b.values_in, "bad_values": b.bad_values, "expired": b.expired,
            "overtaken": b.overtaken}


policies = st.tuples(st.sampled_from([0, 1, 1_000]), st.booleans(),
                     st.sampled_from([0, -7_000, 250_000_000]))


@pytest.mark.parity("rlbridge.server.values_in.bundle")
@PROPS
@given(datagrams=st.lists(st.lists(value_parts(), min_size=1, max_size=6), max_size=6),
       policy=policies)
def test_a_bundle_is_its_parts_each_as_if_alone(datagrams: list[list[Value | Batch]],
                                                policy: tuple[int, bool, int]) -> None:
    fast, general = Side(*policy), Side(*policy)
    try:
        with wall_clock_at(NOW):
            for parts in datagrams:
                values_in.bundle(fast.session, Bundle(list(parts)), fast.told)
                for part in parts:
                    values_in.value_packet(general.session, part.channel, part, general.told)
        assert fast.state() == general.state()
    finally:
        fast.close()
        general.close()


@pytest.mark.parity("rlbridge.server.bindings.Inbound.on_value")
@PROPS
@given(program=st.lists(st.tuples(st.integers(0, 12), stamps, values), max_size=25),
       policy=policies, arrival=st.sampled_from([None, NOW - 500_000]))
def test_one_value_takes_the_same_steps_as_admit(program: list[tuple[int, int, Any]],
                                                 policy: tuple[int, bool, int],
                                                 arrival: int | None) -> None:
    """``on_value`` against its general path written out: ``SequenceTracker.accept``, then
    ``_admit`` of the one value (which measures, applies the policies and publishes)."""
    fast, general = Side(*policy), Side(*policy)
    inline, admit = fast.session.inbound[1], general.session.inbound[1]
    try:
        with wall_clock_at(NOW if arrival is None else arrival):
            for seq, stamp, value in program:
                fast_raised = general_raised = False
                try:
                    # The datagram's arrival, as a bundle passes it, or now when alone.
                    inline.on_value(Value(1, seq, stamp, value), arrival)
                except ValuesRefused:
                    fast_raised = True
                try:
                    if admit.tracker.accept(seq):
                        admit._admit([stamp], [value])
                except ValuesRefused:
                    general_raised = True
                assert fast_raised == general_raised
        assert fast.state() == general.state()
    finally:
        fast.close()
        general.close()


class Wire:
    """A sink that keeps what it is given, and refuses (as a full one would) every value
    ``"refuse"``."""

    def __init__(self) -> None:
        self.packets: list[Packet] = []

    def send(self, packet: Packet, *, data: bool = False) -> bool:
        self.packets.append(packet)
        return not (isinstance(packet, Value) and packet.value == "refuse")

    def dropped(self) -> int:
        return 0

    def congested(self) -> bool:
        return False


def _outbound(redundancy: int, max_batch: int) -> tuple[Outbound, Wire]:
    wire = Wire()
    req = TopicConnect(5, "subscribe", "/parity/out", F64, transport="udp",
                       redundancy=redundancy)
    return Outbound(5, InProcessBus().resolve(F64, "data"), wire, max_batch, redundancy,
                    req), wire


@pytest.mark.parity("rlbridge.server.bindings.Outbound.on_values")
@PROPS
@given(program=st.lists(st.tuples(st.integers(0, 2**62),
                                  st.lists(st.sampled_from([1.5, -2.0, "refuse"]),
                                           max_size=4)), max_size=20),
       redundancy=st.sampled_from([0, 2]), max_batch=st.sampled_from([1, 3, 64]))
def test_a_middleware_batch_goes_out_as_emit_sends_it(program: list[tuple[int, list[Any]]],
                                                      redundancy: int, max_batch: int) -> None:
    """``on_values``'s one value (no redundancy, no latest, no credit) against ``_emit``."""
    fast, fast_wire = _outbound(redundancy, max_batch)
    general, general_wire = _outbound(redundancy, max_batch)
    for stamp, batch in program:
        fast.on_values(batch, stamp)
        if batch:
            general._emit(stamp, batch)
    assert fast_wire.packets == general_wire.packets
    assert (fast.values_out, fast.dropped, fast._seq) == (
        general.values_out, general.dropped, general._seq)
