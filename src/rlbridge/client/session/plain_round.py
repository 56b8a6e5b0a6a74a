"""The send round's short way: what waits in *plain* outgoing channels, as value parts.

A plain channel (``OutgoingChannel.plain``: UDP, and no rate limit, credit, latest, age limit
or redundancy) has nothing between its ring and the wire, so the send thread can take it
without :meth:`~rlbridge.client.channels.outgoing.OutgoingChannel.take`'s policy steps and without a
packet object per value: every value becomes a tuple shaped like the ``Value`` it stands for
(:mod:`rlbridge.wire.bundle`), and the round's parts are encoded by one msgspec call. This is
the hot loop of every send round; the values come out of the ring by the ring's own consumer
step (:mod:`rlbridge.csp.ring`'s seqlock), which is nowhere else.
"""

from __future__ import annotations

from collections.abc import Sequence

from rlbridge.client.channels.outgoing import OutgoingChannel
from rlbridge.csp.ring import EMPTY
from rlbridge.csp.stamped_ring import DRAIN
from rlbridge.wire.bundle import VALUE_TAG, Part


def take_plain(channels: Sequence[OutgoingChannel], parts: list[Part], max_batch: int) -> int:
    """Send thread: what waits in these :attr:`~OutgoingChannel.plain` channels, appended to
    ``parts`` (one round); returns how many values.

    The common case (nothing, or one value since the last round) takes the ring's one pair
    (:meth:`~rlbridge.csp.stamped_ring.StampedRing.take_lone`) and makes one ``Value`` part
    of it. Anything else (several values, or a pair overwritten while it was read) goes
    through :meth:`OutgoingChannel.take_parts`, which drains the ring.
    """
    taken = 0
    empty, drain = EMPTY, DRAIN  # locals: no module lookup per channel
    for ch in channels:
        ring = ch._ring
        value = ring.take_lone()
        if value is empty:
            continue
        if value is not drain:
            seq = ch._next_seq
            ch._next_seq = seq + 1
            parts.append((VALUE_TAG, ch.channel_id, seq, ring.taken_stamp, value))
            taken += 1
            if ch._space.waiting:
                ch._space.ring()
            continue
        taken += ch.take_parts(parts, max_batch)
    return taken
