"""``publish_valid``: the one place a packet's values are checked and refused one by one.

Every packet kind that carries values goes through it, so these are its rules for all of them:
good values are published in order, bad ones counted and named, nothing good is lost for a bad
neighbour, whether the type check (msgspec) or the middleware's own check at publish time (the
ROS 2 adapter raises ``BindingError("BAD_VALUE")``) refuses them.
"""

from __future__ import annotations

from typing import Any

import pytest

from rlbridge.adapters.base import BindingError
from rlbridge.adapters.inproc import InProcessBus
from rlbridge.server.admission import ValuesRefused, publish_valid, value_converter


def convert_for(msg_type: str, field: str | None = "data") -> Any:
    return value_converter(InProcessBus().resolve(msg_type, field))


def test_all_good_values_publish_in_one_call() -> None:
    calls: list[list[Any]] = []
    assert publish_valid(convert_for("std_msgs/msg/Float64"), calls.append, [1.0, 2, 3.5]) == 3
    assert calls == [[1.0, 2.0, 3.5]]


def test_bad_values_cost_only_themselves() -> None:
    calls: list[list[Any]] = []
    with pytest.raises(ValuesRefused) as info:
        publish_valid(convert_for("std_msgs/msg/UInt8"), calls.append, [1, 300, 2, "x", 3])
    assert calls == [[1, 2, 3]]
    refused = info.value
    assert (refused.count, refused.published) == (2, 3)
    assert refused.reason.startswith("2 of 5 values refused; first: ")
    assert "`$[1]`" in refused.reason  # the first bad one, by its index in the packet


def test_a_lone_bad_value_says_just_what_was_wrong() -> None:
    with pytest.raises(ValuesRefused) as info:
        publish_valid(convert_for("std_msgs/msg/Float64"), lambda v: None, [True])
    assert info.value.reason == "Expected `float`, got `bool` - at `$[0]`"
    assert (info.value.count, info.value.published) == (1, 0)


def test_values_the_middleware_refuses_at_publish_time() -> None:
    """The middleware's own check: the batch is retried value by value, good ones kept."""
    published: list[Any] = []

    def publish(values: list[Any]) -> None:
        if any(v > 100 for v in values):  # e.g. a bound only the middleware knows
            raise BindingError("BAD_VALUE", f"{max(values)} is too large for this field")
        published.extend(values)

    with pytest.raises(ValuesRefused) as info:
        publish_valid(convert_for("std_msgs/msg/Int64"), publish, [1, 500, 2])
    assert published == [1, 2]
    assert (info.value.count, info.value.published) == (1, 2)
    assert "500 is too large" in info.value.reason


def test_other_middleware_failures_are_not_value_refusals() -> None:
    def publish(values: list[Any]) -> None:
        raise BindingError("INTERNAL", "the middleware is closed")

    with pytest.raises(BindingError, match="closed"):
        publish_valid(convert_for("std_msgs/msg/Int64"), publish, [1])
