"""The receive thread's inlined run-gathering against ``Receiver._gather`` (any packets).

Two loops of the receive thread join a ``Value`` to its channel's run themselves instead of
calling ``_gather`` (once per value): ``_bundle`` for a bundle's parts and ``_stream`` for
one TCP read's packets. For any sequence of values and batches (several channels, gaps,
duplicates, empty batches) each must hand ``on_values`` exactly the runs the general path
hands it: ``_gather`` per part, ``_dispatch`` per packet. The receiver belongs to a real
:class:`~rlbridge.client.session.connection.Connection`, not opened (no server: nothing is read
from a
socket here; tests/client/test_receive_datagrams.py reads real datagrams).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rlbridge.client.session.connection import Connection
from rlbridge.client.session.receiver import Receiver
from rlbridge.wire import Batch, Value
from rlbridge.wire.link import LinkMonitor

PROPS = settings(deadline=None, max_examples=200, suppress_health_check=[HealthCheck.too_slow])
Run = tuple[int, int, list[int], list[object]]


@st.composite
def packets(draw: st.DrawFn) -> Value | Batch:
    channel = draw(st.integers(1, 3))
    seq = draw(st.integers(0, 10))
    if draw(st.integers(0, 3)):
        return Value(channel, seq, draw(st.integers(0, 99)), draw(st.floats(allow_nan=False)))
    n = draw(st.integers(0, 3))
    return Batch(channel, seq, list(range(seq, seq + n)), [float(seq + i) for i in range(n)])


@contextmanager
def receiver() -> Iterator[tuple[Receiver, list[Run]]]:
    """A receiver of an unopened connection, and the runs it hands to ``on_values``."""
    conn = Connection("127.0.0.1", 9, name="parity", nodelay=True, control="tcp", timeout=5.0)
    conn.link = LinkMonitor(time.monotonic_ns(), 100_000_000)
    runs: list[Run] = []
    conn.on_values = lambda ch, first, stamps, values: runs.append(
        (ch, first, list(stamps), list(values)))
    try:
        yield Receiver(conn, 0, [], conn._wake_r), runs
    finally:
        conn._wake_r.close()
        conn._wake_w.close()


def _copy(packet: Value | Batch) -> Value | Batch:
    """Each path gets its own lists: the receiver keeps a batch's lists as its run."""
    if isinstance(packet, Value):
        return packet
    return Batch(packet.channel, packet.first_seq, list(packet.stamps), list(packet.values))


def _general(program: list[list[Value | Batch]]) -> list[Run]:
    """``_gather`` per part, the runs handed on after each datagram (or read)."""
    with receiver() as (r, runs):
        for group in program:
            for part in map(_copy, group):
                if isinstance(part, Value):
                    r._gather(part.channel, part.seq, [part.stamp_ns], [part.value])
                else:
                    r._gather(part.channel, part.first_seq, part.stamps, part.values)
            r._flush_values()
        return runs


@pytest.mark.parity("rlbridge.client.session.receiver.Receiver._bundle")
@PROPS
@given(st.lists(st.lists(packets(), max_size=8), max_size=5))
def test_a_bundle_gathers_runs_as_its_parts_one_by_one(
        program: list[list[Value | Batch]]) -> None:
    with receiver() as (r, runs):
        for group in program:
            r._bundle([_copy(p) for p in group])
            r._flush_values()
    assert runs == _general(program)


@pytest.mark.parity("rlbridge.client.session.receiver.Receiver._stream")
@PROPS
@given(st.lists(st.lists(packets(), max_size=8), max_size=5))
def test_a_tcp_read_gathers_runs_as_its_packets_dispatched_one_by_one(
        program: list[list[Value | Batch]]) -> None:
    with receiver() as (r, runs):
        for group in program:
            r._stream([_copy(p) for p in group])
            r._flush_values()
    with receiver() as (r, dispatched):
        for group in program:
            for packet in group:
                r._dispatch(_copy(packet))
            r._flush_values()
    assert runs == dispatched == _general(program)
