"""rlbridge._compat: on Python 3.10 the backports behave as 3.11's originals do.

The same assertions run on every Python of the matrix (scripts/test_matrix.sh): on 3.11 and
newer they describe ``enum.StrEnum`` itself, so passing on 3.10 means the backport matches it
where rlbridge relies on it (printing, formatting, comparing, encoding, parsing).
"""

from __future__ import annotations

import enum

import msgspec
import pytest

from rlbridge._compat import BaseExceptionGroup, ExceptionGroup, StrEnum


class Colour(StrEnum):
    RED = "red"
    DARK_BLUE = enum.auto()


def test_members_are_their_values_as_text() -> None:
    assert isinstance(Colour.RED, str)
    assert Colour.RED == "red"
    assert str(Colour.RED) == "red"
    assert f"{Colour.RED}" == "red"
    assert f"{Colour.RED:>5}" == "  red"
    assert "%s" % Colour.RED == "red"  # noqa: UP031 - the old formatting path too
    assert Colour("red") is Colour.RED
    assert Colour.DARK_BLUE == "dark_blue"  # auto() is the lower-cased name


def test_members_encode_and_decode_as_strings() -> None:
    assert msgspec.json.encode(Colour.RED) == b'"red"'
    assert msgspec.json.decode(b'"dark_blue"', type=Colour) is Colour.DARK_BLUE


def test_exception_groups_are_the_builtin_ones_or_the_backport() -> None:
    with pytest.raises(ExceptionGroup) as info:
        raise ExceptionGroup("two", [ValueError("a"), KeyError("b")])
    assert [type(e) for e in info.value.exceptions] == [ValueError, KeyError]
    assert issubclass(ExceptionGroup, BaseExceptionGroup)
