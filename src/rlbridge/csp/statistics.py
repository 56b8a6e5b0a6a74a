"""The counters every channel kind reports (architecture lesson 5: loss is never silent).

A module of its own so that the buffered channel and the rendezvous can both build it without
importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class ChannelStatistics:
    """A snapshot of a channel's counters; exact when the channel is quiet.

    ``written == read + overwritten + dropped + buffered`` once no call is in progress.
    ``stale_reads`` counts non-blocking reads that repeated the latest value;
    ``hrt_blocking_reads`` counts reads by a hard-real-time process that had to wait.
    """

    buffered: int
    overwritten: int
    dropped: int
    written: int
    read: int
    waiting_readers: int
    waiting_writers: int
    closed: bool
    stale_reads: int = 0
    hrt_blocking_reads: int = 0
