"""Receive-side sequence bookkeeping for one channel: duplicates, losses, stale values.

Senders number each channel's values 0, 1, 2, ... A receiver keeps only values newer than the
newest it has delivered. That single rule gives three features at once: duplicates from
redundant UDP datagrams (each datagram repeating the previous k values) are dropped, values
overtaken by newer ones on a reordering path are dropped, and every gap that stays a gap is
counted as lost, so loss is never silent.
"""

from __future__ import annotations


class SequenceTracker:
    """Accepts strictly increasing sequence numbers and counts what it refuses or never saw."""

    __slots__ = ("accepted", "duplicates", "highest", "lost", "stale")

    def __init__(self) -> None:
        self.highest = -1
        self.accepted = 0
        self.duplicates = 0
        self.stale = 0
        self.lost = 0

    def restart(self) -> None:
        """The sender numbers from 0 again (a new binding); the counters keep their totals."""
        self.highest = -1

    def accept(self, seq: int) -> bool:
        """True if ``seq`` is new and newer than everything delivered; counts the rest."""
        highest = self.highest
        if seq > highest:
            if highest >= 0:
                self.lost += seq - highest - 1
            self.highest = seq
            self.accepted += 1
            return True
        if seq == highest:
            self.duplicates += 1
        else:
            self.stale += 1
        return False

    def accept_run(self, first_seq: int, count: int) -> int:
        """For a batch ``first_seq .. first_seq+count-1``: index of the first new value.

        Returns ``count`` when the whole batch is old. Values before the index were delivered
        already (duplicates) or overtaken (stale); the rest are new and in order.
        """
        if count <= 0:  # an empty batch delivers nothing and must not move ``highest``
            return 0
        last = first_seq + count - 1
        highest = self.highest
        if last <= highest:
            self.duplicates += count
            return count
        start = max(0, highest + 1 - first_seq)
        self.duplicates += start
        if highest >= 0 and first_seq > highest + 1:
            self.lost += first_seq - highest - 1
        self.highest = last
        self.accepted += count - start
        return start
