"""Exceptions and warnings of the CSP layer.

They separate "you misused the API" (:class:`ChannelMisuseError`, :class:`ValueError` from
constructors) from "the channel was closed" (:class:`ChannelClosed`) and from "nothing
is there right now" (:class:`WouldBlock`, :class:`NoValueYet`), and every one names
the channel so the message tells a person which wire to look at.
"""

from __future__ import annotations


class ChannelError(Exception):
    """Base class of every channel error; ``channel`` is the channel's name."""

    def __init__(self, channel: str, message: str) -> None:
        super().__init__(message)
        self.channel = channel


class ChannelClosed(ChannelError):
    """The channel was closed with ``close()``.

    Raised by writes after the close, by reads once a closed channel has no buffered
    value left, and in every party that was blocked on the channel when it closed.
    """

    def __init__(self, channel: str) -> None:
        super().__init__(channel, f"channel {channel!r} is closed")


class WouldBlock(ChannelError):
    """A ``try_*`` twin could not complete without waiting."""

    def __init__(self, channel: str, operation: str) -> None:
        super().__init__(channel, f"{operation} on channel {channel!r} would block")
        self.operation = operation


class NoValueYet(ChannelError, LookupError):
    """A non-blocking channel without ``initial`` was read before any value arrived."""

    def __init__(self, channel: str) -> None:
        super().__init__(
            channel,
            f"non-blocking channel {channel!r} has never received a value and has no "
            "initial value: give it one where it is made, bridge.subscribe(..., initial=0.0) "
            "(or Channel(..., initial=...)), or catch NoValueYet until the first value",
        )


class ChannelMisuseError(ChannelError, RuntimeError):
    """Two threads used the same end of a one-to-one buffered channel at the same time.

    The buffered channels are lock-free single-producer/single-consumer rings; two
    concurrent writers (or readers) would lose or duplicate values without a trace,
    so the overlap is detected and refused instead.
    """

    def __init__(self, channel: str, end: str) -> None:
        super().__init__(
            channel,
            f"two threads used the {end} end of buffered channel {channel!r} concurrently; "
            f"a buffered channel has exactly one {end} at a time (use one channel per "
            "writer, or an MpscRing to fan several writers in)",
        )
        self.end = end


class SecondWriterError(ChannelMisuseError):
    """A second thread wrote an outgoing channel whose first writer thread is still alive."""

    def __init__(self, topic: str, owner: int, intruder: int) -> None:
        super().__init__(f"{topic} out", "writer")
        self.args = (
            f"outgoing channel {topic!r} is written by thread {owner}; thread {intruder} "
            "wrote it too. Its ring buffer has a single producer: two writers would lose "
            "values without a trace. Publish one channel per writer thread, or hand values "
            "to the one writer through a local Channel.",)


class RealTimeWarning(RuntimeWarning):
    """A hard-real-time rule could not be honoured (blocking read, no RT scheduling)."""
