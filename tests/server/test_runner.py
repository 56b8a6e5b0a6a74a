"""rlbridge.server.runner.run_on_loop: asyncio.Runner on 3.11+, the same steps by hand on 3.10."""

from __future__ import annotations

import asyncio

import pytest

from rlbridge.server import new_event_loop
from rlbridge.server.runner import run_on_loop


def test_returns_the_result_on_a_loop_from_the_factory_and_closes_it() -> None:
    made: list[asyncio.AbstractEventLoop] = []

    def factory() -> asyncio.AbstractEventLoop:
        made.append(new_event_loop(use_uvloop=False))
        return made[-1]

    async def main() -> int:
        assert asyncio.get_running_loop() is made[0]
        return 42

    assert run_on_loop(main(), factory) == 42
    assert len(made) == 1
    assert made[0].is_closed()


def test_tasks_left_running_are_cancelled_before_the_loop_closes() -> None:
    cancelled: list[bool] = []

    async def forever() -> None:
        try:
            await asyncio.sleep(3600)
        except asyncio.CancelledError:
            cancelled.append(True)
            raise

    async def main() -> None:
        asyncio.get_running_loop().create_task(forever())
        await asyncio.sleep(0)

    run_on_loop(main(), lambda: new_event_loop(use_uvloop=True))
    assert cancelled == [True]


def test_an_exception_of_main_propagates() -> None:
    async def main() -> None:
        raise ValueError("from main")

    with pytest.raises(ValueError, match="from main"):
        run_on_loop(main(), lambda: new_event_loop(use_uvloop=False))
