"""Tests of the three channel kinds: semantics, closing, statistics, threads, allocation."""

from __future__ import annotations

import contextlib
import threading
import tracemalloc
import warnings
from collections.abc import Callable, Sequence
from itertools import pairwise
from typing import Any, overload

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pattern_support import wait_until

from rlbridge.csp.channel import Channel, Doorbell
from rlbridge.csp.process import Code
from rlbridge.errors import (
    ChannelClosed,
    ChannelMisuseError,
    NoValueYet,
    RealTimeWarning,
    WouldBlock,
)

JOIN = 10.0  # generous bound for joins and waits; only reached when a test fails


class Background:
    """Run ``fn`` in a thread and keep its result or exception for the test to inspect."""

    def __init__(self, fn: Callable[[], object]) -> None:
        self.result: object = None
        self.error: BaseException | None = None
        self._fn = fn
        self.thread = threading.Thread(target=self._main)
        self.thread.start()

    def _main(self) -> None:
        try:
            self.result = self._fn()
        except BaseException as exc:
            self.error = exc

    def join(self) -> object:
        self.thread.join(JOIN)
        assert not self.thread.is_alive(), "background call did not finish"
        return self.result


# -- construction ---------------------------------------------------------------------------


def test_constructor_rejects_meaningless_combinations() -> None:
    with pytest.raises(ValueError, match="buffer_size"):
        Channel(-1)
    with pytest.raises(ValueError, match="non-blocking"):
        Channel(0, blocking=False)
    with pytest.raises(ValueError, match="initial"):
        Channel(2, initial=0)


# -- rendezvous -----------------------------------------------------------------------------


def test_rendezvous_write_returns_only_after_a_reader_took_the_value() -> None:
    chan: Channel[str] = Channel(name="rv")
    writer = Background(lambda: chan.write("x"))
    wait_until(lambda: chan.statistics().waiting_writers == 1, "the writer blocks")
    assert writer.thread.is_alive()
    assert chan.read(timeout=JOIN) == "x"
    writer.join()
    assert writer.error is None
    stats = chan.statistics()
    assert (stats.written, stats.read, stats.buffered, stats.waiting_writers) == (1, 1, 0, 0)


def test_rendezvous_read_waits_for_a_writer() -> None:
    chan: Channel[int] = Channel()
    reader = Background(lambda: chan.read(timeout=JOIN))
    wait_until(lambda: chan.statistics().waiting_readers == 1, "the reader blocks")
    chan.write(7, timeout=JOIN)
    assert reader.join() == 7


def test_rendezvous_timeouts_withdraw_the_offer() -> None:
    chan: Channel[int] = Channel(name="lonely")
    with pytest.raises(TimeoutError, match="lonely"):
        chan.write(1, timeout=0.01)
    with pytest.raises(WouldBlock):
        chan.try_read()  # the timed-out value is not left behind
    with pytest.raises(TimeoutError):
        chan.read(timeout=0.01)
    assert chan.statistics().written == 0


def test_rendezvous_try_twins() -> None:
    chan: Channel[int] = Channel()
    with pytest.raises(WouldBlock, match="try_write"):
        chan.try_write(1)  # nobody is waiting to read
    assert chan.read_many() == []
    reader = Background(lambda: chan.read(timeout=JOIN))
    wait_until(lambda: chan.statistics().waiting_readers == 1, "the reader blocks")
    chan.try_write(2)
    assert reader.join() == 2
    writer = Background(lambda: chan.write(3, timeout=JOIN))
    wait_until(lambda: len(chan) == 1, "the writer offers")
    assert chan.try_read() == 3
    writer.join()
    assert writer.error is None


def test_rendezvous_close_wakes_both_sides() -> None:
    chan: Channel[int] = Channel(name="c")
    reader = Background(chan.read)
    wait_until(lambda: chan.statistics().waiting_readers == 1, "the reader blocks")
    chan.close()
    reader.join()
    assert isinstance(reader.error, ChannelClosed)
    assert reader.error.channel == "c"

    chan2: Channel[int] = Channel()
    writer = Background(lambda: chan2.write(1))
    wait_until(lambda: chan2.statistics().waiting_writers == 1, "the writer blocks")
    chan2.close()
    writer.join()
    assert isinstance(writer.error, ChannelClosed)
    with pytest.raises(ChannelClosed):
        chan2.write(2)
    with pytest.raises(ChannelClosed):
        chan2.read()


def test_rendezvous_offer_made_by_try_write_and_lost_to_close_is_counted() -> None:
    chan: Channel[int] = Channel()
    rv = chan._rv
    assert rv is not None
    # White-box: a reader that has been counted as waiting but has not yet taken the
    # offer when close() wins the lock; with threads this ordering is not controllable.
    rv.waiting_readers = 1
    chan.try_write(1)
    rv.waiting_readers = 0
    chan.close()
    stats = chan.statistics()
    assert (stats.written, stats.read, stats.dropped, stats.buffered) == (1, 0, 1, 0)
    assert stats.written == stats.read + stats.dropped + stats.buffered


def test_rendezvous_many_writers_many_readers_each_value_once() -> None:
    chan: Channel[int] = Channel()
    per_writer, writers = 500, 2
    got: list[int] = []
    lock = threading.Lock()

    def write_all(base: int) -> None:
        for i in range(per_writer):
            chan.write(base + i, timeout=JOIN)

    def read_all() -> None:
        while True:
            try:
                value = chan.read(timeout=JOIN)
            except ChannelClosed:
                return
            with lock:
                got.append(value)

    threads = [threading.Thread(target=write_all, args=(w * 10_000,)) for w in range(writers)]
    threads += [threading.Thread(target=read_all) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads[:writers]:
        thread.join(JOIN)
    chan.close()
    for thread in threads[writers:]:
        thread.join(JOIN)
    assert sorted(got) == sorted(w * 10_000 + i for w in range(writers) for i in range(per_writer))
    stats = chan.statistics()
    assert (stats.written, stats.read, stats.dropped) == (1000, 1000, 0)


# -- blocking buffered -----------------------------------------------------------------------


def test_blocking_buffered_writer_overwrites_oldest_and_counts() -> None:
    chan: Channel[int] = Channel(3)
    for i in range(5):
        chan.write(i)  # never blocks
    stats = chan.statistics()
    assert (stats.buffered, stats.overwritten, stats.written) == (3, 2, 5)
    assert [chan.read(), chan.read(), chan.read()] == [2, 3, 4]
    with pytest.raises(WouldBlock):
        chan.try_read()
    with pytest.raises(TimeoutError):
        chan.read(timeout=0.01)


def test_blocking_buffered_reader_waits_for_a_write() -> None:
    chan: Channel[str] = Channel(2)
    reader = Background(lambda: chan.read(timeout=JOIN))
    wait_until(lambda: chan.statistics().waiting_readers == 1, "the reader blocks")
    chan.write("hello")
    assert reader.join() == "hello"


def test_blocking_buffered_close_drains_then_raises() -> None:
    chan: Channel[int] = Channel(4, name="b")
    chan.write(1)
    chan.write(2)
    chan.close()
    with pytest.raises(ChannelClosed):
        chan.write(3)
    assert chan.read() == 1
    assert chan.read_many() == [2]
    with pytest.raises(ChannelClosed):
        chan.read()
    with pytest.raises(ChannelClosed):
        chan.read_many()
    with pytest.raises(ChannelClosed):
        chan.try_read()
    assert chan.statistics().closed


def test_close_wakes_a_blocked_buffered_reader() -> None:
    chan: Channel[int] = Channel(1)
    reader = Background(chan.read)
    wait_until(lambda: chan.statistics().waiting_readers == 1, "the reader blocks")
    chan.close()
    reader.join()
    assert isinstance(reader.error, ChannelClosed)


def test_read_many_and_deliver_many() -> None:
    chan: Channel[int] = Channel(4)
    chan.deliver_many(list(range(6)))
    assert chan.read_many(3) == [2, 3, 4]
    assert chan.read_many() == [5]
    assert chan.read_many() == []
    stats = chan.statistics()
    assert (stats.written, stats.read, stats.overwritten) == (6, 4, 2)


# -- non-blocking buffered -------------------------------------------------------------------


def test_non_blocking_repeats_latest_or_initial() -> None:
    chan: Channel[float] = Channel(1, blocking=False, initial=0.0)
    assert chan.read() == 0.0
    chan.write(1.5)
    assert chan.read() == 1.5
    assert chan.read() == 1.5  # nothing new: the latest value again
    assert chan.try_read() == 1.5
    assert chan.read_many() == []  # but batch readers only get new values
    chan.write(2.5)
    chan.write(3.5)  # buffer of one: 2.5 is overwritten
    assert chan.read() == 3.5
    stats = chan.statistics()
    assert (stats.read, stats.stale_reads, stats.overwritten, stats.written) == (2, 3, 1, 3)


def test_non_blocking_without_any_value_says_so() -> None:
    chan: Channel[int] = Channel(2, blocking=False, name="setpoint")
    with pytest.raises(NoValueYet, match="never received a value") as info:
        chan.read()
    assert isinstance(info.value, LookupError)
    assert info.value.channel == "setpoint"


def test_non_blocking_close_drains_then_raises() -> None:
    chan: Channel[int] = Channel(2, blocking=False, initial=0)
    chan.write(4)
    chan.close()
    assert chan.read() == 4
    with pytest.raises(ChannelClosed):
        chan.read()


def test_non_blocking_write_never_rings() -> None:
    rings: list[int] = []

    class CountingBell(Doorbell):
        __slots__ = ()

        def ring(self) -> None:
            rings.append(1)
            super().ring()

    chan: Channel[int] = Channel(2, blocking=False, initial=0, doorbell=CountingBell())
    blocking: Channel[int] = Channel(2, doorbell=CountingBell())
    for i in range(100):
        chan.write(i)
        chan.read()
        blocking.write(i)
        blocking.read()
    assert rings == []  # nobody waited, so no write took the doorbell's lock
    reader = Background(lambda: blocking.read(timeout=JOIN))
    wait_until(lambda: blocking.statistics().waiting_readers == 1, "the reader blocks")
    blocking.write(-1)
    assert reader.join() == -1
    assert len(rings) == 1


# -- statistics identity ---------------------------------------------------------------------

chan_ops = st.lists(
    st.one_of(
        st.tuples(st.just("write"), st.integers()),
        st.tuples(st.just("deliver"), st.lists(st.integers(), max_size=6)),
        st.tuples(st.just("read"), st.none()),
        st.tuples(st.just("read_many"), st.one_of(st.none(), st.integers(0, 4))),
    ),
    max_size=40,
)


@settings(max_examples=100, deadline=None)
@given(size=st.integers(1, 4), blocking=st.booleans(), program=chan_ops)
def test_statistics_account_for_every_value(
    size: int, blocking: bool, program: list[tuple[str, Any]]
) -> None:
    chan: Channel[int] = Channel(size) if blocking else Channel(size, blocking=False, initial=-1)
    taken: list[int] = []
    for name, arg in program:
        if name == "write":
            chan.write(arg)
        elif name == "deliver":
            chan.deliver_many(arg)
        elif name == "read":
            with contextlib.suppress(WouldBlock):
                taken.append(chan.try_read())
        else:
            taken.extend(chan.read_many(arg))
        s = chan.statistics()
        assert s.written == s.read + s.overwritten + s.dropped + s.buffered
    s = chan.statistics()
    assert len(taken) == s.read + s.stale_reads  # every value handed out is accounted for
    assert s.stale_reads == 0 or not blocking


# -- one writer, one reader ------------------------------------------------------------------


class _Reentrant(Sequence[int]):
    """A batch whose length is computed by writing to the channel: a second writer at the
    exact moment the first one holds the writer end."""

    def __init__(self, chan: Channel[int]) -> None:
        self._chan = chan

    def __len__(self) -> int:
        self._chan.write(99)
        return 0

    @overload
    def __getitem__(self, index: int) -> int: ...
    @overload
    def __getitem__(self, index: slice) -> Sequence[int]: ...
    def __getitem__(self, index: int | slice) -> int | Sequence[int]:
        raise IndexError(index)


def test_overlapping_writers_are_refused_not_lost() -> None:
    chan: Channel[int] = Channel(4, name="shared")
    with pytest.raises(ChannelMisuseError, match="writer end of buffered channel 'shared'"):
        chan.deliver_many(_Reentrant(chan))
    chan.write(1)  # the end was released: normal use continues
    assert chan.read() == 1


def test_second_reader_while_one_is_blocked_is_refused() -> None:
    chan: Channel[int] = Channel(1, name="one-reader")
    reader = Background(lambda: chan.read(timeout=JOIN))
    wait_until(lambda: chan.statistics().waiting_readers == 1, "the reader blocks")
    with pytest.raises(ChannelMisuseError, match="reader"):
        chan.read()
    chan.write(5)
    assert reader.join() == 5


def test_ends_may_change_threads_between_calls() -> None:
    chan: Channel[int] = Channel(2)
    Background(lambda: chan.write(1)).join()
    chan.write(2)
    assert Background(chan.read).join() == 1
    assert chan.read() == 2


# -- hard-real-time reporting ----------------------------------------------------------------


def test_hrt_process_blocking_on_a_read_is_counted_and_warned_once() -> None:
    chan: Channel[int] = Channel(1, name="cmd")
    got: list[int] = []

    def body() -> None:
        got.append(chan.read(timeout=JOIN))
        got.append(chan.read(timeout=JOIN))

    feeder = Background(lambda: _feed(chan, [1, 2]))
    with pytest.warns(RealTimeWarning, match="'hrt_loop' blocked reading channel 'cmd'") as rec:
        Code(body, name="hrt_loop", hrt=True).run()
    feeder.join()
    assert got == [1, 2]
    assert len([w for w in rec if issubclass(w.category, RealTimeWarning)]) == 1
    assert chan.statistics().hrt_blocking_reads == 2


def test_rendezvous_read_in_hrt_process_is_reported() -> None:
    chan: Channel[int] = Channel(name="sync")
    feeder = Background(lambda: _feed(chan, [1]))
    with pytest.warns(RealTimeWarning, match="sync"):
        Code(lambda: chan.read(timeout=JOIN), hrt=True).run()
    feeder.join()
    assert chan.statistics().hrt_blocking_reads == 1


def test_non_hrt_blocking_and_hrt_non_blocking_reads_are_not_reported() -> None:
    blocking: Channel[int] = Channel(1)
    latest: Channel[int] = Channel(1, blocking=False, initial=0)
    feeder = Background(lambda: _feed(blocking, [1]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Code(lambda: blocking.read(timeout=JOIN), name="srt").run()
        Code(latest.read, name="hrt", hrt=True).run()
    feeder.join()
    assert blocking.statistics().hrt_blocking_reads == 0


def _feed(chan: Channel[int], values: list[int]) -> None:
    """Write each value once the reader has taken the previous one and blocks again."""
    for done, value in enumerate(values):

        def blocked_again(done: int = done) -> bool:
            stats = chan.statistics()
            return stats.read == done and stats.waiting_readers == 1

        wait_until(blocked_again, "the reader blocks")
        chan.write(value, timeout=JOIN)


# -- threads: no lost wake-up ----------------------------------------------------------------


@pytest.mark.usefixtures("frequent_switches")
def test_ping_pong_over_buffered_channels_never_loses_a_wake_up() -> None:
    # Every round needs one wake-up each way; a lost one would end in a TimeoutError.
    rounds = 3_000
    ping: Channel[int] = Channel(1)
    pong: Channel[int] = Channel(1)

    def echo() -> None:
        for _ in range(rounds):
            pong.write(ping.read(timeout=JOIN) + 1)

    echoer = Background(echo)
    value = 0
    for _ in range(rounds):
        ping.write(value)
        value = pong.read(timeout=JOIN)
    echoer.join()
    assert echoer.error is None
    assert value == rounds


@pytest.mark.usefixtures("frequent_switches")
def test_overwriting_writer_and_blocking_reader_threads() -> None:
    n = 100_000
    chan: Channel[int] = Channel(8)
    got: list[int] = []

    def reader() -> None:
        while True:
            try:
                got.append(chan.read(timeout=JOIN))
            except ChannelClosed:
                return

    consumer = Background(reader)
    for i in range(n):
        chan.write(i)
    chan.close()
    consumer.join()
    assert consumer.error is None
    assert all(a < b for a, b in pairwise(got))
    assert got[-1] == n - 1
    stats = chan.statistics()
    assert stats.written == n == stats.read + stats.overwritten


# -- allocation ------------------------------------------------------------------------------


def _net_bytes(operation: Callable[[int], None], count: int) -> int:
    operation(count)  # warm-up
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        operation(count)
        return tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("kind", ["blocking", "non-blocking", "stale"])
def test_hrt_path_allocates_nothing_in_steady_state(kind: str) -> None:
    chan: Channel[float] = (
        Channel(4) if kind == "blocking" else Channel(4, blocking=False, initial=0.0)
    )
    value = 1.25
    write, read = chan.write, chan.read

    def operation(count: int) -> None:
        for _ in range(count):
            if kind != "stale":
                write(value)
            read()

    # A few counter ints stay alive at the end; the total does not grow with the count.
    small, large = _net_bytes(operation, 10_000), _net_bytes(operation, 40_000)
    assert small <= 256
    assert large <= 256
