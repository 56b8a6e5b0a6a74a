"""The send round's short way, without a network: the send thread's bell, which channels are
``plain``, and ``take_plain`` (one part per value, sequence numbers, overwrites counted)."""

from __future__ import annotations

import threading

import msgspec
import pytest

from rlbridge import OutgoingChannel
from rlbridge.csp.bell import SendBell
from rlbridge.csp.plain_round import take_plain
from rlbridge.wire import Batch, Value
from rlbridge.wire.bundle import VALUE_TAG, Part, as_packet

WAIT = 20.0


def outgoing(channel: int = 1, **kw: object) -> OutgoingChannel:
    options: dict[str, object] = {"transport": "udp", "immediate": False, "buffer_size": 8,
                                  "doorbell": SendBell()}
    options.update(kw)
    return OutgoingChannel(channel, "/cmd", "std_msgs/msg/Float64", "data", **options)  # type: ignore[arg-type]


# -- the bell ------------------------------------------------------------------------------


def test_a_ring_wakes_the_waiting_thread() -> None:
    bell = SendBell()
    state = {"work": False}
    woke = threading.Event()

    def waiter() -> None:
        bell.wait_for(lambda: state["work"])
        woke.set()

    t = threading.Thread(target=waiter)
    t.start()
    while not bell.waiting:  # the waiter announced itself before it checks the state
        threading.Event().wait(0.001)
    state["work"] = True
    bell.ring()
    assert woke.wait(WAIT)
    t.join(WAIT)
    assert bell.waiting == 0


def test_a_ring_without_a_waiter_is_kept_once_and_rings_collapse() -> None:
    bell = SendBell()
    bell.ring()
    bell.ring()  # a second pending ring is no error and no second wake-up
    checks: list[int] = []

    def predicate() -> bool:
        checks.append(1)
        return False

    assert bell.wait_for(predicate, timeout=0.05) is False
    # The pending ring let the wait return once: the predicate was checked again after it.
    assert len(checks) >= 2
    assert bell.waiting == 0


def test_wait_returns_at_once_when_the_work_is_there() -> None:
    bell = SendBell()
    assert bell.wait_for(lambda: True, timeout=None) is True
    assert bell.wait_for(lambda: True, timeout=0.0) is True
    assert bell.wait_for(lambda: False, timeout=0.0) is False


def test_no_wake_up_is_lost_between_producer_and_waiter() -> None:
    """The producer rings only while the waiter waits; 500 hand-offs, none missed (a missed
    one would leave the waiter asleep with work waiting: its bounded wait fails)."""
    bell = SendBell()
    rounds = 500
    state = {"asked": 0, "done": 0}
    caught_up = threading.Semaphore(0)
    failed: list[int] = []

    def consumer() -> None:
        while state["done"] < rounds:
            if not bell.wait_for(lambda: state["asked"] != state["done"], timeout=WAIT):
                failed.append(state["asked"])
                return
            state["done"] = state["asked"]
            caught_up.release()

    t = threading.Thread(target=consumer)
    t.start()
    for _ in range(rounds):
        state["asked"] += 1
        if bell.waiting:
            bell.ring()
        assert caught_up.acquire(timeout=WAIT), f"hand-off {state['asked']} was lost"
    t.join(WAIT)
    assert not failed
    assert state["done"] == rounds


# -- which channels take the short way -----------------------------------------------------


@pytest.mark.parametrize(("options", "plain"), [
    ({}, True),
    ({"immediate": True}, True),
    ({"transport": "tcp"}, False),
    ({"latest": True}, False),
    ({"max_age_ms": 5}, False),
    ({"redundancy": 1}, False),
    ({"max_rate_hz": 100.0}, False),
    ({"transport": "tcp", "flow": True}, False),
])
def test_plain_means_no_policy_between_ring_and_wire(options: dict[str, object],
                                                      plain: bool) -> None:
    assert outgoing(**options).plain is plain


# -- take_plain ----------------------------------------------------------------------------


def test_one_value_per_channel_becomes_one_value_part_each() -> None:
    chans = [outgoing(i) for i in range(3)]
    parts: list[Part] = []
    for round_ in range(3):
        for ch in chans:
            ch.write(float(round_ * 10 + ch.channel_id))
        assert take_plain(chans, parts, 64) == 3
    assert [p[0] for p in parts] == [VALUE_TAG] * 9
    packets = [as_packet(p) for p in parts]
    assert all(isinstance(p, Value) for p in packets)
    # (channel, seq, value): numbered per channel from 0, in order.
    assert [(p.channel, p.seq, p.value) for p in packets if isinstance(p, Value)] == [
        (c, r, float(r * 10 + c)) for r in range(3) for c in range(3)]
    # The same bytes as the packet it stands for.
    enc = msgspec.msgpack.encode
    assert all(enc(part) == enc(as_packet(part)) for part in parts)
    assert take_plain(chans, parts, 64) == 0  # nothing new: nothing taken
    assert len(parts) == 9


def test_several_values_become_batches_of_at_most_max_batch() -> None:
    ch = outgoing(buffer_size=16)
    ch.write_many([float(i) for i in range(5)])
    parts: list[Part] = []
    assert take_plain([ch], parts, 2) == 5
    packets = [as_packet(p) for p in parts]
    assert [(p.first_seq, p.values) for p in packets if isinstance(p, Batch)] == [
        (0, [0.0, 1.0]), (2, [2.0, 3.0]), (4, [4.0])]
    ch.write_many([5.0, 6.0])
    parts.clear()
    assert take_plain([ch], parts, 1) == 2  # one value per packet: Values
    assert [as_packet(p) for p in parts] == [
        Value(1, 5, parts[0][3], 5.0), Value(1, 6, parts[1][3], 6.0)]


def test_an_overwritten_ring_is_counted_and_leaves_no_sequence_gap() -> None:
    ch = outgoing(buffer_size=2)
    for i in range(5):
        ch.write(float(i))
    parts: list[Part] = []
    assert take_plain([ch], parts, 64) == 2
    (batch,) = [as_packet(p) for p in parts]
    assert isinstance(batch, Batch)
    assert (batch.first_seq, batch.values) == (0, [3.0, 4.0])
    stats = ch.statistics()
    assert (stats.written, stats.read, stats.overwritten) == (5, 2, 3)
    ch.write(5.0)
    parts.clear()
    assert take_plain([ch], parts, 64) == 1
    assert parts[0][2] == 2  # numbered on from the values that were sent


def test_a_full_ring_waiter_is_woken_by_the_take() -> None:
    ch = outgoing(buffer_size=1)
    ch.write(1.0)
    assert ch.writable == 0
    got: list[bool] = []
    t = threading.Thread(target=lambda: got.append(ch.wait_writable(WAIT)))
    t.start()
    while not ch._space.waiting:
        threading.Event().wait(0.001)
    parts: list[Part] = []
    assert take_plain([ch], parts, 64) == 1
    t.join(WAIT)
    assert got == [True]
