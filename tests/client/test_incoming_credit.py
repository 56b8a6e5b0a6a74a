"""The credit an :class:`IncomingChannel` grants, across re-binds, against a server that sends
exactly what it is granted (docs/protocol.md 10.5).

Any program of sends, reads and re-binds (a reconnect with values still unread in the ring)
must leave the ring never overwritten and the reader every value once, in order: the first
credit of a re-bind is the ring's free room (``restart_sequence``), later ones what the send
thread grants (``credit_due``/``credit_limit``, as ``SendLoop._grant_credit`` does). The same
on a live server, killed and restarted: tests/client/test_reconnect.py.
"""

from __future__ import annotations

import time

from hypothesis import given, settings
from hypothesis import strategies as st

from rlbridge.client.channels.incoming import IncomingChannel
from rlbridge.csp.bell import SendBell

Op = tuple[str, int]
OPS = st.lists(st.one_of(st.tuples(st.just("send"), st.integers(1, 20)),
                         st.tuples(st.just("read"), st.integers(1, 20)),
                         st.tuples(st.just("rebind"), st.just(0))), max_size=60)


@settings(max_examples=300, deadline=None)
@given(ring=st.integers(1, 16), ops=OPS)
def test_credit_never_lets_the_ring_overflow_across_rebinds(ring: int, ops: list[Op]) -> None:
    ch = IncomingChannel(1, "/t", "std_msgs/msg/Int64", "data", transport="tcp",
                         blocking=True, buffer_size=ring, credit_bell=SendBell())
    limit, next_seq, produced = ch.credited, 0, 0  # the server's view of this binding
    got: list[int] = []
    for op, n in ops:
        if op == "send":  # the server sends what the credit allows
            count = min(n, limit - next_seq)
            if count > 0:
                ch.deliver(next_seq, [time.time_ns()] * count,
                           list(range(produced, produced + count)))
                next_seq += count
                produced += count
        elif op == "read":
            got += ch.read_many(n)
            if ch.credit_due():  # the send thread's grant
                ch.credited = limit = max(limit, ch.credit_limit())
        else:  # a new session: the server numbers from 0, the request carries the room
            limit, next_seq = ch.restart_sequence(), 0
            assert limit == ring - len(ch)
        assert ch.health().overwritten == 0
        assert len(ch) <= ring
    got += ch.read_many()
    assert got == list(range(produced))
    assert ch.lost == 0
