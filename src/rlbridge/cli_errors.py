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
    """Print one line on stderr and exit non-zero: the CLI's only way to report an error."""
    typer.echo(f"rlbridge: error: {message}", err=True)
    return typer.Exit(code)


def one_line_errors(fn: F) -> F:
    """Known failures become one line on stderr; only real bugs keep their traceback."""
    from rlbridge.adapters import AdapterUnavailable, BindingError
    from rlbridge.server import ServerError
    from rlbridge.wire import RlbridgeError

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except (RlbridgeError, ServerError, AdapterUnavailable) as exc:
            raise fail(str(exc)) from None
        except BindingError as exc:
            raise fail(exc.reason) from None
        except OSError as exc:
            raise fail(exc.strerror or str(exc)) from None
        except ValueError as exc:
            raise fail(str(exc)) from None
        except KeyboardInterrupt:
            raise typer.Exit(130) from None

    return wrapper  # type: ignore[return-value]
