"""The steal-matched comparison: each run against the reference runs with the nearest steal."""

from __future__ import annotations

import random

from hypothesis import given
from hypothesis import strategies as st

from benchmarks.jitter.steal import matched_ci, matched_delta, matched_deltas, neighbours


def test_each_run_is_compared_with_the_nearest_reference_runs() -> None:
    refs = [(0.0, 100.0), (10.0, 110.0), (20.0, 120.0),
            (100.0, 1000.0), (110.0, 1100.0), (120.0, 1200.0)]
    assert neighbours(len(refs)) == 3
    # steal 105: the nearest are 100, 110 and 120 (not 20), median 1100
    # steal 0: 0, 10, 20, median 110
    assert matched_deltas([(105.0, 1150.0), (0.0, 100.0)], refs) == [50.0, -10.0]
    assert matched_deltas([(500.0, 1.0)], refs) == [1.0 - 1100.0]  # beyond the last: the top 3
    assert matched_deltas([(1.0, 1.0)], []) == []


def test_an_offset_hidden_under_steal_noise_is_recovered() -> None:
    """p99 driven by steal (x30 between runs) plus +150 us: pairing in time could not see it."""
    rng = random.Random(1)

    def host() -> float:
        return rng.choice([0.0, 10.0, 20.0, 50.0, 100.0, 200.0, 400.0])

    def p99(steal: float) -> float:
        return 100.0 + 8.0 * steal + rng.gauss(0, 20)

    refs = [(s, p99(s)) for s in (host() for _ in range(120))]
    same = [(s, p99(s)) for s in (host() for _ in range(9))]
    worse = [(s, p99(s) + 150.0) for s in (host() for _ in range(9))]
    assert abs(matched_delta([(same, refs)])) < 30  # the same loop: no difference
    low, high = matched_ci([(same, refs)])
    assert high - low < 80  # against steal spreading p99 over 100 .. 3300 us
    low, high = matched_ci([(worse, refs)])
    assert low > 60  # the added 150 us is resolved
    assert 100 < matched_delta([(worse, refs)]) < 200


@given(st.lists(st.tuples(st.integers(0, 300), st.integers(50, 5000)), min_size=1, max_size=40),
       st.lists(st.tuples(st.integers(0, 300), st.integers(50, 5000)), min_size=1, max_size=20))
def test_matched_reference_is_one_of_the_reference_values_range(
        refs: list[tuple[int, int]], runs: list[tuple[int, int]]) -> None:
    """Whatever the steal, the stand-in reference p99 lies within the reference runs' range."""
    fr = [(float(s), float(p)) for s, p in refs]
    fx = [(float(s), float(p)) for s, p in runs]
    lowest, highest = min(p for _, p in fr), max(p for _, p in fr)
    for (_, p99), delta in zip(fx, matched_deltas(fx, fr), strict=True):
        assert lowest <= p99 - delta <= highest


def test_groups_keep_their_own_references() -> None:
    """Two runs on two hosts: each run's scenario is matched with its own host's references."""
    calm = [(0.0, 100.0)] * 9
    noisy = [(0.0, 1000.0)] * 9
    groups = [([(0.0, 110.0)] * 5, calm), ([(0.0, 1010.0)] * 5, noisy)]
    assert matched_delta(groups) == 10.0
    assert matched_ci(groups) == (10.0, 10.0)
