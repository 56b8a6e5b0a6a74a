"""The few Python 3.11 features rlbridge uses, made available on Python 3.10.

Ubuntu 22.04 (ROS 2 Humble) ships Python 3.10, and control boards often run it, so rlbridge
supports 3.10 to 3.13. Anything newer than 3.10 that rlbridge needs goes through this module,
so that each backport exists once and disappears in one place when 3.10 is dropped. Typing
names (``Self``, ``Unpack``) come from ``typing_extensions``, which pyproject declares for 3.10;
``BaseExceptionGroup`` from the ``exceptiongroup`` backport, declared the same way.

This module imports only ``enum``, ``sys`` and ``typing`` (and the two backports on 3.10): every
layer, the sans-IO ``wire/`` included, may import it. ``asyncio.Runner``'s backport lives with
the rest of the asyncio code, in :mod:`rlbridge.server.runner`.
"""

from __future__ import annotations

import enum
import sys
from typing import Any

__all__ = ["BaseExceptionGroup", "ExceptionGroup", "Self", "StrEnum", "Unpack"]

if sys.version_info >= (3, 11):
    from builtins import BaseExceptionGroup, ExceptionGroup
    from enum import StrEnum
    from typing import Self, Unpack
else:  # pragma: no cover - exercised by the Python 3.10 leg of scripts/test.sh
    from exceptiongroup import BaseExceptionGroup, ExceptionGroup
    from typing_extensions import Self, Unpack

    class StrEnum(str, enum.Enum):
        """Python 3.11's ``enum.StrEnum``: members are ``str`` and print as their value."""

        def __str__(self) -> str:
            return str(self.value)

        def __format__(self, format_spec: str) -> str:
            return str.__format__(str(self.value), format_spec)

        @staticmethod
        def _generate_next_value_(name: str, start: int, count: int,
                                  last_values: list[Any]) -> str:
            return name.lower()

