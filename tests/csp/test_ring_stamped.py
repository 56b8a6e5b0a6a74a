"""The stamped ring (the outgoing channel's): pairs taken whole, through the ring's own step.

``StampedRing`` keeps no consumer code of its own beyond copying two slot lists: its
``drain_stamped`` and ``take_lone`` (the send round's common case) go through ``SpscRing``'s
seqlock step. Any program of writes and takes must agree with a bounded deque of pairs, every
counter included; and a pair the producer overwrites while ``take_lone`` reads it is never
returned (a forced preemption, as tests/csp/test_ring.py does for ``pop``).
"""

from __future__ import annotations

from collections import deque
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rlbridge._compiled import STATE
from rlbridge.csp.ring import EMPTY
from rlbridge.csp.stamped_ring import DRAIN, StampedRing

#: ``("push", n)`` writes n pairs (one call per pair, or one batch when n > 1 and ``batch``);
#: ``("lone", 0)`` is ``take_lone``; ``("drain", k)`` drains at most k (-1: everything).
Op = tuple[str, int, bool]
programs = st.lists(st.one_of(
    st.tuples(st.just("push"), st.integers(1, 6), st.booleans()),
    st.tuples(st.just("lone"), st.just(0), st.just(False)),
    st.tuples(st.just("drain"), st.integers(-1, 4), st.just(False)),
), max_size=40)


@settings(max_examples=300, deadline=None)
@given(capacity=st.integers(1, 5), program=programs)
def test_any_program_matches_a_deque_of_pairs(capacity: int, program: list[Op]) -> None:
    ring = StampedRing(capacity)
    model: deque[tuple[int, int]] = deque(maxlen=capacity)
    written = overwritten = popped = 0
    n = 0
    for op, arg, batch in program:
        if op == "push":
            pairs = [(1000 + n + i, n + i) for i in range(arg)]
            n += arg
            if batch:  # one stamp for the batch, as write_many gives it
                stamp = pairs[0][0]
                pairs = [(stamp, v) for _, v in pairs]
                ring.push_many_stamped(stamp, [v for _, v in pairs])
            else:
                for stamp, value in pairs:
                    ring.push_stamped(stamp, value)
            overwritten += max(0, len(model) + len(pairs) - capacity)
            model.extend(pairs)
            written += len(pairs)
        elif op == "lone":
            got = ring.take_lone()
            if not model:
                assert got is EMPTY
            elif got is DRAIN:  # several wait (or the producer lapped the reader): drain
                stamps, values = ring.drain_stamped()
                assert list(zip(stamps, values, strict=True)) == list(model)
                popped += len(model)
                model.clear()
            else:
                assert len(model) == 1
                assert (ring.taken_stamp, got) == model.popleft()
                popped += 1
        else:
            take = len(model) if arg < 0 else min(arg, len(model))
            stamps, values = ring.drain_stamped(None if arg < 0 else arg)
            expected = [model.popleft() for _ in range(take)]
            assert list(zip(stamps, values, strict=True)) == expected
            popped += take
        assert (ring.written, ring.popped, ring.overwritten, len(ring)) == (
            written, popped, overwritten, len(model))


class _Preempting(list[Any]):
    """A slot list that lets the producer run once, right after a slot is read."""

    def __init__(self, items: list[Any]) -> None:
        super().__init__(items)
        self.after_get: Any = None

    def __getitem__(self, index: Any) -> Any:
        value = super().__getitem__(index)
        hook, self.after_get = self.after_get, None
        if hook is not None:
            hook()
        return value


@pytest.mark.skipif(STATE.startswith("compiled"), reason="the compiled ring's list reads "
                    "call no subclass hook: the preemption is forced on the Python ring")
@pytest.mark.parametrize("extra", [1, 2, 5])
def test_a_pair_overwritten_while_take_lone_reads_it_is_not_returned(extra: int) -> None:
    ring = StampedRing(2)
    slots = _Preempting([None, None])
    ring._slots = slots  # white-box: the preemption point
    ring.push_stamped(100, "old")
    # While take_lone holds "old"'s slot, the producer laps it (claims it before storing).
    slots.after_get = lambda: [ring.push_stamped(200 + i, f"new{i}") for i in range(extra + 1)]
    assert ring.take_lone() is DRAIN
    stamps, values = ring.drain_stamped()
    newest = list(range(extra + 1))[-2:]
    assert values == [f"new{i}" for i in newest]
    assert stamps == [200 + i for i in newest]  # each stamp with its own value
    assert ring.written == ring.popped + ring.overwritten + len(ring) == extra + 2
