"""Write-time type checks: a wrong value fails where it is written, not later at the server.

The server answers a publish channel's ``TopicConnect`` with the JSON Schema of the values it
accepts (``TopicAck.schema``, written out from the msgspec type it validates with). At bind time
:func:`compile_check` turns that schema into a :class:`ValueCheck`: a frozenset of the Python
types that pass unchanged (``float`` for a ``Float64`` field) and a slower ``coerce`` for the
rest. ``OutgoingChannel.write`` pays one ``type(value) in accept`` test per write (tens of
nanoseconds, docs/benchmarks.md); only other values reach ``coerce``, which returns the value to
send (an ``int`` for a float field becomes a ``float``, a NumPy scalar a Python number) or
raises :class:`~rlbridge.errors.WrongValueType`.

The rules are the server's (msgspec's strict mode, the ROS types): an integer is a valid float,
a bool is neither an integer nor a float, integers are range-checked, strings length-checked,
whole messages are dicts whose keys must be fields of the type (missing ones take defaults).
The check never refuses what the server accepts: a schema construct this module does not know
accepts anything, and the server still checks (and refuses only the bad values of a batch).
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import msgspec

Coerce = Callable[[Any], Any]

_INT_MIN = -(2**63)
_UINT_MAX = 2**64 - 1


class Mismatch(Exception):
    """A value (or a part of one, at ``path``) that cannot be the schema's type."""

    def __init__(self, expected: str, value: Any, path: str = "") -> None:
        super().__init__(expected)
        self.expected = expected
        self.value = value
        self.path = path


class ValueCheck(NamedTuple):
    """``accept``: types written unchanged without a further test (but ``within``, if given:
    the integers a value of an accepted type must be among); ``coerce``: all others."""

    accept: frozenset[type]
    coerce: Coerce
    expected: str
    within: range | None = None


def _anything(value: Any) -> Any:
    return value


#: For a channel without a schema (an older server): nothing passes the fast test, and the
#: slow path accepts everything unchanged.
UNCHECKED = ValueCheck(frozenset(), _anything, "anything")


def compile_check(schema: Mapping[str, Any] | None) -> ValueCheck:
    """The check of a ``TopicAck.schema``; :data:`UNCHECKED` when there is none."""
    if not schema:
        return UNCHECKED
    defs = schema.get("$defs", {})
    try:
        return _compile(schema, defs if isinstance(defs, Mapping) else {})
    except (RecursionError, TypeError, ValueError, AttributeError):
        return UNCHECKED  # a schema this module cannot read (cyclic, odd types): no check


def _compile(schema: Mapping[str, Any], defs: Mapping[str, Any]) -> ValueCheck:
    ref = schema.get("$ref")
    if isinstance(ref, str) and ref.startswith("#/$defs/") and ref[8:] in defs:
        return _compile(defs[ref[8:]], defs)
    kind = schema.get("type")
    if kind == "number":
        return _number(schema)
    if kind == "integer":
        return _integer(schema)
    if kind == "boolean":
        return ValueCheck(frozenset({bool}), _refuse("a bool"), "a bool")
    if kind == "string" and "contentEncoding" not in schema:
        return _string(schema)
    if kind == "array":
        return _array(schema, defs)
    if kind == "object" and isinstance(schema.get("properties"), Mapping):
        return _object(schema, defs)
    return UNCHECKED


def _refuse(expected: str) -> Coerce:
    def coerce(value: Any) -> Any:
        raise Mismatch(expected, value)

    return coerce


def _real(value: Any) -> float | None:
    """``value`` as a float if it is a number other than a bool (NumPy scalars included)."""
    if isinstance(value, bool) or type(value).__name__ == "bool_":
        return None
    if isinstance(value, float | int):
        return float(value)
    try:
        return float(operator.index(value))
    except TypeError:
        pass
    as_float = getattr(value, "__float__", None)
    if as_float is not None and hasattr(value, "dtype"):  # a NumPy floating scalar
        result: float = as_float()
        return result
    return None


def _number(schema: Mapping[str, Any]) -> ValueCheck:
    lo, hi = schema.get("minimum"), schema.get("maximum")
    if not all(b is None or type(b) in (int, float) for b in (lo, hi)):
        raise TypeError("schema bounds of a number must be numbers")
    expected = "a float (an int is fine)" if lo is None and hi is None else \
        f"a float in {lo}..{hi}"

    def coerce(value: Any) -> Any:
        number = float(value) if type(value) is int else _real(value)
        if number is None or (lo is not None and not number >= lo) or (
                hi is not None and not number <= hi):
            raise Mismatch(expected, value)
        return number

    bounded = lo is not None or hi is not None
    return ValueCheck(frozenset() if bounded else frozenset({float}), coerce, expected)


def _integer(schema: Mapping[str, Any]) -> ValueCheck:
    # MessagePack carries integers from -2**63 to 2**64 - 1 (a uint64's top is beyond what the
    # schema can say): nothing outside would even encode.
    lo = max(_bound(schema.get("minimum"), _INT_MIN), _INT_MIN)
    hi = min(_bound(schema.get("maximum"), _UINT_MAX), _UINT_MAX)
    expected = f"an int in {lo}..{hi}"

    def coerce(value: Any) -> Any:
        if type(value) is int:
            if lo <= value <= hi:
                return value
            raise Mismatch(expected, value)
        if isinstance(value, bool) or type(value).__name__ == "bool_":
            raise Mismatch(expected, value)
        try:
            number = operator.index(value)
        except TypeError:
            raise Mismatch(expected, value) from None
        if not lo <= number <= hi:
            raise Mismatch(expected, value)
        return number

    # ``value in range(...)`` is one C-level comparison for an int: the fast path stays fast.
    return ValueCheck(frozenset({int}), coerce, expected, range(lo, hi + 1))


def _bound(value: Any, default: int) -> int:
    if type(value) is not int:
        if value is None:
            return default
        raise TypeError(f"schema bound {value!r} is not an integer")
    return value


def _string(schema: Mapping[str, Any]) -> ValueCheck:
    lo, hi = _bound(schema.get("minLength"), 0), schema.get("maxLength")
    hi = None if hi is None else _bound(hi, 0)
    expected = "a str" if hi is None else f"a str of at most {hi} characters"
    if lo:
        expected = f"a str of {lo}..{hi if hi is not None else ''} characters"

    def coerce(value: Any) -> Any:
        if not isinstance(value, str) or len(value) < lo or (hi is not None and len(value) > hi):
            raise Mismatch(expected, value)
        return str(value)

    plain = not lo and hi is None
    return ValueCheck(frozenset({str}) if plain else frozenset(), coerce, expected)


def _array(schema: Mapping[str, Any], defs: Mapping[str, Any]) -> ValueCheck:
    items = schema.get("items")
    item = _compile(items, defs) if isinstance(items, Mapping) else UNCHECKED
    lo, hi = _bound(schema.get("minItems"), 0), schema.get("maxItems")
    hi = None if hi is None else _bound(hi, 0)
    size = "" if hi is None and not lo else f" of {lo}..{hi if hi is not None else ''}" \
        if lo != hi else f" of {lo}"
    expected = f"a list{size} of {item.expected}"
    accept, coerce_item = (item.accept if item.within is None else frozenset()), item.coerce

    def coerce(value: Any) -> Any:
        if isinstance(value, str | bytes | Mapping) or not hasattr(value, "__iter__"):
            raise Mismatch(expected, value)
        tolist = getattr(value, "tolist", None)  # array.array, numpy.ndarray
        values = list(tolist() if tolist is not None else value)
        if len(values) < lo or (hi is not None and len(values) > hi):
            raise Mismatch(expected, value)
        if all(type(v) in accept for v in values):
            return values
        out = []
        for index, v in enumerate(values):
            try:
                out.append(v if type(v) in accept else coerce_item(v))
            except Mismatch as exc:
                raise Mismatch(exc.expected, exc.value, _join(f"[{index}]", exc.path)) from None
        return out

    return ValueCheck(frozenset(), coerce, expected)


def _object(schema: Mapping[str, Any], defs: Mapping[str, Any]) -> ValueCheck:
    fields = {name: _compile(sub, defs) for name, sub in schema["properties"].items()}
    closed = schema.get("additionalProperties") is False
    required = tuple(schema.get("required", ()))
    expected = "a dict of " + (", ".join(fields) if fields else "no fields")

    def coerce(value: Any) -> Any:
        if type(value) is not dict:  # the common case skips two (slow) isinstance tests
            if isinstance(value, msgspec.Struct):
                value = msgspec.to_builtins(value)
            if not isinstance(value, Mapping):
                raise Mismatch(expected, value)
        out: dict[str, Any] | None = None
        for key, v in value.items():
            check = fields.get(key)
            if check is None:
                if closed:
                    raise Mismatch(f"a field name it has ({', '.join(fields)})", key, str(key))
                continue
            if type(v) in check.accept and (check.within is None or v in check.within):
                continue
            try:
                new = check.coerce(v)
            except Mismatch as exc:
                raise Mismatch(exc.expected, exc.value, _join(key, exc.path)) from None
            if new is not v:
                if out is None:
                    out = dict(value)
                out[key] = new
        for key in required:  # ROS messages have none: every field has a default
            if key not in value:
                raise Mismatch(f"field {key!r} (it has no default)", value)
        return out if out is not None else value if type(value) is dict else dict(value)

    return ValueCheck(frozenset(), coerce, expected)


def _join(head: str, tail: str) -> str:
    if not tail:
        return head
    return head + tail if tail.startswith("[") else f"{head}.{tail}"
