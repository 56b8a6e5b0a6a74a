"""Run one coroutine on a new event loop of rlbridge's choice, on Python 3.10 to 3.13.

``asyncio.Runner(loop_factory=...)`` runs a coroutine on a loop that a factory makes (uvloop or
asyncio's, chosen per loop, no global policy); it is new in Python 3.11. On 3.10 the same steps
are taken by hand, the ones ``asyncio.run`` takes on close: cancel what is left, finish the
async generators and the default executor, close the loop.
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

_T = TypeVar("_T")


def run_on_loop(main: Coroutine[Any, Any, _T],
                loop_factory: Callable[[], asyncio.AbstractEventLoop]) -> _T:
    """Run ``main`` to completion on a new loop from ``loop_factory``, then close that loop.

    ``asyncio.Runner(loop_factory=...)`` on 3.11 and newer (Ctrl-C cancels ``main``); on 3.10,
    the same steps ``asyncio.run`` takes, with the loop from the factory (uvloop or asyncio's).
    """
    if sys.version_info >= (3, 11):
        with asyncio.Runner(loop_factory=loop_factory) as runner:
            return runner.run(main)
    loop = loop_factory()
    try:
        return loop.run_until_complete(main)
    finally:
        try:
            _cancel_all_tasks(loop)
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.run_until_complete(loop.shutdown_default_executor())
        finally:
            loop.close()


def _cancel_all_tasks(loop: asyncio.AbstractEventLoop) -> None:
    """Cancel what ``main`` left running and wait for it, as ``asyncio.run`` does on close."""
    pending = asyncio.all_tasks(loop)
    for task in pending:
        task.cancel()
    if not pending:
        return
    loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
    for task in pending:
        if not task.cancelled() and task.exception() is not None:
            loop.call_exception_handler({
                "message": "unhandled exception during shutdown",
                "exception": task.exception(),
                "task": task,
            })
