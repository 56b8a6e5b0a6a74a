"""Which of a packet's values may be published: type checks, and refusing only the bad ones.

A value that is not of its channel's type must cost only itself. The happy path validates a
whole batch in one msgspec call (``value_converter``); only when that fails are the values
checked one by one, so the good ones are published and each bad one is counted and named in
one ``Error(BAD_VALUE)`` whose ``values`` field says how many were refused. The same goes for
a middleware that refuses a value at publish time (the ROS 2 adapter's own range checks, as a
:class:`~rlbridge.adapters.base.BindingError` ``BAD_VALUE``). :func:`publish_valid` is the one
place this happens: every packet kind that carries values (``Value``, ``Batch``, and any
multi-channel packet) goes through it per channel.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any, get_args, get_origin

import msgspec

from rlbridge.adapters.base import BindingError, ValueSpec

Convert = Callable[[list[Any]], list[Any]]
Publish = Callable[[list[Any]], None]

#: Batches up to this long are checked value by value in Python before calling msgspec.
_EXACT_MAX = 8
_CONSTRAINTS = ("gt", "lt", "multiple_of", "pattern", "min_length", "max_length", "tz")


class ValuesRefused(Exception):
    """Some values of a packet were not of the channel's type; the others were published.

    Raised *after* publishing the good ones; ``count`` is how many were refused,
    ``published`` how many went out, and ``reason`` names the first refused one (its index
    in the packet's values, and what was wrong).
    """

    def __init__(self, count: int, published: int, reason: str) -> None:
        super().__init__(reason)
        self.count = count
        self.published = published
        self.reason = reason


def value_converter(spec: ValueSpec) -> Convert:
    """Validate a list of decoded values against the channel's type, in one msgspec call.

    Whole messages are validated as their Struct and handed on as plain dicts, the adapter's
    currency. Raises ``msgspec.ValidationError`` naming the offending element.
    """
    list_type = list[spec.python_type]  # type: ignore[name-defined]
    if isinstance(spec.python_type, type) and issubclass(spec.python_type, msgspec.Struct):

        def convert_messages(values: list[Any]) -> list[Any]:
            result: list[Any] = msgspec.to_builtins(msgspec.convert(values, list_type))
            return result

        return convert_messages

    exact = exact_check(spec.python_type)

    def convert_fields(values: list[Any]) -> list[Any]:
        # A few values of exactly the right type (the one-value-per-packet case) skip msgspec,
        # whose fixed cost per call is ~1 us; the result is the same, and anything else
        # (an int for a float, a bound to check) takes the msgspec path and its errors.
        if exact is not None and len(values) <= _EXACT_MAX and all(map(exact, values)):
            return values
        result: list[Any] = msgspec.convert(values, list_type)
        return result

    return convert_fields


def value_schema(spec: ValueSpec) -> dict[str, Any] | None:
    """The JSON Schema of the values ``spec`` accepts, for the ``TopicAck`` of a publish channel.

    It is what msgspec validates against, written out: a client that refuses what the schema
    refuses refuses nothing the server would accept. ``None`` for a type msgspec cannot
    describe (the client then checks nothing, and the server still does).
    """
    try:
        schema: dict[str, Any] = msgspec.json.schema(spec.python_type)
    except (TypeError, ValueError):
        return None
    return schema


def exact_check(python_type: Any) -> Callable[[Any], bool] | None:
    """A predicate true for values msgspec would accept unchanged, or None if not simple.

    Covers plain ``float``, ``bool`` and ``str`` and integers bounded by ``Meta(ge, le)`` (the
    ROS integer types); ``type(v) is ...`` so ``True`` is no int and ``1`` no float here.
    """
    if python_type in (float, bool, str):
        return lambda v: type(v) is python_type
    if get_origin(python_type) is not Annotated:
        return None
    base, *metas = get_args(python_type)
    if base is not int or not all(isinstance(m, msgspec.Meta) for m in metas):
        return None
    if any(getattr(m, c) is not None for m in metas for c in _CONSTRAINTS):
        return None
    lo = max((m.ge for m in metas if m.ge is not None), default=None)
    hi = min((m.le for m in metas if m.le is not None), default=None)
    if lo is None or hi is None:
        return None
    return lambda v: type(v) is int and lo <= v <= hi


def publish_valid(convert: Convert, publish: Publish, values: list[Any]) -> int:
    """Publish every value of ``values`` that is of the channel's type; return how many.

    Raises :class:`ValuesRefused` after publishing when some were not (the caller answers
    with one error packet); never drops a good value for a bad neighbour. A middleware that
    refuses a value raises ``BindingError("BAD_VALUE")`` before publishing any of the call's
    values (the adapters' contract), so retrying value by value publishes none twice.
    """
    try:
        converted = convert(values)
    except msgspec.ValidationError:
        return _one_by_one(convert, publish, values)
    try:
        publish(converted)
    except BindingError as exc:
        if exc.code != "BAD_VALUE":
            raise
        return _one_by_one(convert, publish, values)
    return len(converted)


def _one_by_one(convert: Convert, publish: Publish, values: list[Any]) -> int:
    """The slow path of a packet with a bad value in it: check, then publish, each alone."""
    good: list[Any] = []
    problems: list[str] = []
    for index, value in enumerate(values):
        try:
            good.extend(convert([value]))
        except msgspec.ValidationError as exc:
            problems.append(str(exc).replace("`$[0]`", f"`$[{index}]`"))
    if good:
        try:
            publish(good)
        except BindingError as exc:  # the middleware's own check: find which, keep the rest
            if exc.code != "BAD_VALUE":
                raise
            published = []
            for value in good:
                try:
                    publish([value])
                except BindingError as one:
                    if one.code != "BAD_VALUE":
                        raise
                    problems.append(one.reason)
                else:
                    published.append(value)
            good = published
    if problems:
        n = len(values)
        head = (problems[0] if n == 1
                else f"{len(problems)} of {n} values refused; first: {problems[0]}")
        raise ValuesRefused(len(problems), len(good), head) from None
    return len(good)
