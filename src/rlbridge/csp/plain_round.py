"""The send round's short way: what waits in *plain* outgoing channels, as value parts.

A plain channel (``OutgoingChannel.plain``: UDP, and no rate limit, credit, latest, age limit
or redundancy) has nothing between its ring and the wire, so the send thread can take it
without :meth:`~rlbridge.csp.outgoing.OutgoingChannel.take`'s policy steps and without a
packet object per value: every value becomes a tuple shaped like the ``Value`` it stands for
(:mod:`rlbridge.wire.bundle`), and the round's parts are encoded by one msgspec call. This is
the hot loop of every send round, so it reads the channel's ring directly (the consumer step
of :mod:`rlbridge.csp.ring`'s seqlock, for one pair) instead of calling into it.
"""

from __future__ import annotations

from collections.abc import Sequence

from rlbridge.csp.outgoing import OutgoingChannel
from rlbridge.wire.bundle import VALUE_TAG, Part


def take_plain(channels: Sequence[OutgoingChannel], parts: list[Part], max_batch: int) -> int:
    """Send thread: what waits in these :attr:`~OutgoingChannel.plain` channels, appended to
    ``parts`` (one round); returns how many values.

    The common case (nothing, or one value since the last round) is inline, a dozen
    operations per channel: the ring's consumer step for one pair (rlbridge.csp.ring's
    seqlock: take the slot, then check that ``_claim`` did not reach it) and one ``Value``
    part. Anything else (several values, or a pair overwritten while it was
    read) goes through :meth:`OutgoingChannel.take_parts`, which drains the ring properly.
    """
    taken = 0
    for ch in channels:
        ring = ch._ring
        tail = ring._tail
        count = ring._head - tail
        if not count:
            continue
        if count == 1:
            cap = ring._cap
            i = tail % cap
            stamp, value = ring._stamps[i], ring._slots[i]
            if ring._claim - cap - tail <= 0:  # not overwritten while we read it
                ring._tail = tail + 1
                seq = ch._next_seq
                ch._next_seq = seq + 1
                parts.append((VALUE_TAG, ch.channel_id, seq, stamp, value))
                taken += 1
                if ch._space.waiting:
                    ch._space.ring()
                continue
        taken += ch.take_parts(parts, max_batch)
    return taken
