"""How every ``rlbridge`` command reports a failure: one line on stderr and an exit status.

Shared by the main app (:mod:`rlbridge.cli`) and the groups it adds (``demo``, ``bench``,
``netem``); it lives apart from the app so a group can use it without importing the app that
imports the group.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, TypeVar

import typer

__all__ = ["fail", "one_line_errors"]

F = TypeVar("F", bound=Callable[..., Any])


def fail(message: str, code: int = 1) -> typer.Exit:
    """Print one line on stderr and exit non-zero: the CLI's only way to report an error.

    Code 1: the command could not do what was asked; 2: the command line itself is wrong;
    130 (from :func:`one_line_errors`): interrupted by Ctrl-C.
    """
    typer.echo(f"rlbridge: error: {message}", err=True)
    return typer.Exit(code)


def one_line_errors(fn: F) -> F:
    """Known failures become one line on stderr; only real bugs keep their traceback."""
    from rlbridge.adapters import AdapterUnavailable, BindingError
    from rlbridge.errors import RemoteError
    from rlbridge.server import ServerError
    from rlbridge.wire import RlbridgeError

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except RemoteError as exc:  # the server's reason, without the protocol's code name
            raise fail(exc.reason) from None
        except (RlbridgeError, ServerError, AdapterUnavailable) as exc:
            raise fail(str(exc)) from None
        except BindingError as exc:
            raise fail(exc.reason) from None
        except OSError as exc:  # a file the user named: say which
            reason = exc.strerror or str(exc)
            raise fail(f"{exc.filename}: {reason}" if exc.filename else reason) from None
        except ValueError as exc:
            raise fail(str(exc)) from None
        except KeyboardInterrupt:
            raise typer.Exit(130) from None

    return wrapper  # type: ignore[return-value]
