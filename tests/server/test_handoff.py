"""The hand-off from middleware threads to the event loop: full means dropped, and counted."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Sequence
from typing import Any

from rlbridge.server.handoff import LoopHandoff


def test_batches_past_the_limit_are_counted_for_their_channel() -> None:
    """A batch that finds the hand-off full is dropped; its values reach the channel's
    ``on_drop`` on the loop thread (not only the server-wide batch count)."""
    loop = asyncio.new_event_loop()
    try:
        handoff = LoopHandoff(loop, limit=2)
        delivered: dict[str, list[Any]] = {"a": [], "b": []}
        dropped: dict[str, int] = {"a": 0, "b": 0}
        drop_threads: set[int] = set()

        def deliver(name: str) -> Any:
            def fn(values: Sequence[Any], _stamp_ns: int) -> None:
                delivered[name] += values
            return fn

        def on_drop(name: str) -> Any:
            def fn(count: int) -> None:
                drop_threads.add(threading.get_ident())
                dropped[name] += count
            return fn

        a = handoff.wrap(deliver("a"), on_drop("a"))
        b = handoff.wrap(deliver("b"), on_drop("b"))
        unmetered = handoff.wrap(deliver("b"))

        def burst() -> None:  # the loop is not running: everything waits in the hand-off
            a([1, 2])
            b([3])
            a([4, 5, 6])
            b([7, 8])
            unmetered([9])

        worker = threading.Thread(target=burst)
        worker.start()
        worker.join()
        loop.call_soon(loop.stop)
        loop.run_forever()
    finally:
        loop.close()
    assert delivered == {"a": [1, 2], "b": [3]}
    assert dropped == {"a": 3, "b": 2}
    assert handoff.dropped_batches == 3
    assert drop_threads == {threading.get_ident()}


def test_calls_on_the_loop_thread_skip_the_hand_off() -> None:
    loop = asyncio.new_event_loop()
    try:
        handoff = LoopHandoff(loop, limit=0)
        got: list[Any] = []
        handoff.wrap(lambda values, _stamp: got.extend(values), lambda n: got.append(-n))([1])
    finally:
        loop.close()
    assert got == [1]
    assert handoff.dropped_batches == 0
