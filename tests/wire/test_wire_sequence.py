"""SequenceTracker against a reference model (hypothesis), plus the documented examples."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

from hypothesis import given, settings
from hypothesis import strategies as st

from rlbridge.wire.sequence import SequenceTracker


@dataclass
class Model:
    """The rule, written the slow and obvious way: keep only values newer than the newest.

    ``lost`` counts the numbers skipped between two delivered values (numbers before the first
    delivered value are not counted: the receiver cannot know the stream started earlier).
    """

    delivered: list[int]
    duplicates: int = 0
    stale: int = 0

    def accept(self, seq: int) -> bool:
        newest = self.delivered[-1] if self.delivered else -1
        if seq > newest:
            self.delivered.append(seq)
            return True
        if seq == newest:
            self.duplicates += 1
        else:
            self.stale += 1
        return False

    @property
    def lost(self) -> int:
        d = self.delivered
        return sum(b - a - 1 for a, b in itertools.pairwise(d))


def check(tracker: SequenceTracker, model: Model) -> None:
    assert tracker.accepted == len(model.delivered)
    assert tracker.highest == (model.delivered[-1] if model.delivered else -1)
    assert tracker.lost == model.lost


seqs = st.integers(0, 60)


@settings(deadline=None, max_examples=300)
@given(st.lists(seqs, max_size=60))
def test_accept_matches_the_model(script: list[int]) -> None:
    tracker, model = SequenceTracker(), Model([])
    for seq in script:
        assert tracker.accept(seq) == model.accept(seq)
        check(tracker, model)
        assert tracker.duplicates == model.duplicates
        assert tracker.stale == model.stale
    # Everything offered is accounted for exactly once.
    assert tracker.accepted + tracker.duplicates + tracker.stale == len(script)


runs = st.lists(st.tuples(seqs, st.integers(0, 8)), max_size=30)


@settings(deadline=None, max_examples=300)
@given(runs)
def test_accept_run_equals_accepting_each_value(script: list[tuple[int, int]]) -> None:
    """A batch is its values one by one: same deliveries; old ones counted (as duplicates)."""
    tracker, model = SequenceTracker(), Model([])
    for first, count in script:
        start = tracker.accept_run(first, count)
        expected = [model.accept(first + i) for i in range(count)]
        # The new values are exactly a suffix of the batch, starting at ``start``.
        assert expected == [i >= start for i in range(count)]
        assert 0 <= start <= count
        check(tracker, model)
        assert tracker.duplicates == model.duplicates + model.stale


@settings(deadline=None, max_examples=300)
@given(st.lists(st.one_of(seqs.map(lambda s: (s, None)), st.tuples(seqs, st.integers(0, 8))),
                max_size=40))
def test_values_and_batches_mixed(script: list[tuple[int, int | None]]) -> None:
    tracker, model = SequenceTracker(), Model([])
    for first, count in script:
        if count is None:
            assert tracker.accept(first) == model.accept(first)
        else:
            start = tracker.accept_run(first, count)
            assert [model.accept(first + i) for i in range(count)] == [
                i >= start for i in range(count)]
        check(tracker, model)
        assert tracker.duplicates + tracker.stale == model.duplicates + model.stale


def test_redundant_datagrams() -> None:
    """Each datagram repeats the previous two values (redundancy 2); one datagram is lost."""
    tracker = SequenceTracker()
    assert tracker.accept_run(0, 1) == 0
    assert tracker.accept_run(0, 2) == 1
    # datagram [0, 1, 2] lost
    assert tracker.accept_run(1, 3) == 1  # values 1, 2, 3: 1 was delivered, 2 and 3 are new
    assert (tracker.accepted, tracker.lost, tracker.highest) == (4, 0, 3)
    assert tracker.accept_run(10, 3) == 0  # 4..9 never arrive
    assert tracker.lost == 6
    assert tracker.accept_run(5, 3) == 3  # overtaken: dropped
    assert tracker.accepted == 7


def test_empty_run_changes_nothing() -> None:
    tracker = SequenceTracker()
    assert tracker.accept(3)
    assert tracker.accept_run(100, 0) == 0
    assert (tracker.highest, tracker.lost, tracker.accepted) == (3, 0, 1)
    assert tracker.accept(4)
