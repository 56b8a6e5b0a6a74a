"""Which logging handlers write to a stream that is closed (a test's guard, and its subject).

A handler left on a logger after the stream it holds was closed (a ``CliRunner``'s stderr, a
test's capture) turns every later record of the process into a ``--- Logging error ---``
traceback, printed under whichever test happens to log next: the guard in ``conftest.py`` fails
the test that left it instead.
"""

from __future__ import annotations

import logging


def on_closed_streams() -> list[tuple[logging.Logger, logging.Handler]]:
    """Each handler of any logger (the root included) whose stream is closed, with its logger."""
    loggers: list[logging.Logger] = [logging.getLogger()]
    loggers += [lg for lg in list(logging.Logger.manager.loggerDict.values())
                if isinstance(lg, logging.Logger)]
    return [(lg, handler) for lg in loggers for handler in list(lg.handlers)
            if getattr(getattr(handler, "stream", None), "closed", False)]
