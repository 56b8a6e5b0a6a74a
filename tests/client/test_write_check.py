"""A wrong value fails at ``write`` (a TypeError naming topic, field and type), against a live
server; and the write-time check agrees with the server's own check, value by value."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from rlbridge import Bridge, WrongValueType
from rlbridge.adapters.inproc import InProcessBus
from rlbridge.csp.value_check import compile_check
from rlbridge.server.admission import value_converter
from rlbridge.wire import TopicAck
from write_agreement import assert_write_check_agrees

F64 = "std_msgs/msg/Float64"
TWIST = "geometry_msgs/msg/Twist"


@pytest.mark.parametrize("value", ["abc", None, [1, 2], True, {"data": 1.0}, b"\x00"])
def test_a_wrong_value_raises_at_write(bridge: Callable[..., Bridge], value: Any) -> None:
    b = bridge()
    out = b.publish("/wc/f", F64, transport="tcp")
    with pytest.raises(TypeError) as info:
        out.write(value)
    assert isinstance(info.value, WrongValueType)
    text = str(info.value)
    assert "'/wc/f'" in text
    assert "std_msgs/msg/Float64 field data" in text
    assert "needs a float" in text
    assert out.health().rejected == 1
    assert out.pending() == 0  # nothing entered the buffer


def test_good_values_pass_and_ints_become_floats(bridge: Callable[..., Bridge],
                                                 wait_until: Callable[..., Any]) -> None:
    b = bridge()
    inc = b.subscribe("/wc/ok", F64, transport="tcp", blocking=True, buffer_size=8)
    out = b.publish("/wc/ok", F64, transport="tcp")
    out.write(1.5)
    out.write(2)
    out.write_many([3, 4.5])
    got = [inc.read(timeout=5) for _ in range(4)]
    assert got == [1.5, 2.0, 3.0, 4.5]
    assert all(type(v) is float for v in got)
    assert out.health().rejected == 0


def test_write_many_refuses_the_whole_call_naming_the_value(
        bridge: Callable[..., Bridge]) -> None:
    b = bridge()
    out = b.publish("/wc/many", "std_msgs/msg/UInt8", transport="tcp")
    with pytest.raises(TypeError, match=r"needs an int in 0\.\.255, got int 300"):
        out.write_many([1, 2, 300])
    assert out.pending() == 0


def test_whole_message_fields_are_checked(bridge: Callable[..., Bridge]) -> None:
    b = bridge()
    out = b.publish("/wc/twist", TWIST, None, transport="tcp")
    out.write({"linear": {"x": 1, "y": 0.5}})  # an int for a float is fine; missing: defaults
    with pytest.raises(TypeError, match=r"field linear\.x\) needs a float"):
        out.write({"linear": {"x": "fast"}})
    with pytest.raises(TypeError, match=r"field linear\.w\) needs a field name"):
        out.write({"linear": {"w": 1.0}})
    with pytest.raises(TypeError, match="needs a dict of linear, angular"):
        out.write(3.0)
    assert out.health().rejected == 3


def test_server_refusals_count_in_health(bridge: Callable[..., Bridge],
                                         wait_until: Callable[..., Any]) -> None:
    """A value the write check cannot know is bad (a channel bound before the schema was
    known, as with an older server) is refused by the server alone; health() counts it."""
    b = bridge()
    out = b.publish("/wc/old", F64, transport="tcp")
    out.bound(TopicAck(out.channel_id, F64))  # no schema: nothing checked at write
    out.write_many([1.0, "abc", None, 2.0])
    wait_until(lambda: out.health().rejected == 2)
    channel = b.server_stats()["session"]["channels"][str(out.channel_id)]
    assert (channel["values_in"], channel["bad_values"]) == (2, 2)


# The agreement table: for each (type, field, value), the write check refuses exactly what
# the server's msgspec validation refuses.
AGREEMENT = [
    (F64, "data", [1.0, 0, -3, 2**70, True, "1", None, [1.0], float("nan")]),
    ("std_msgs/msg/Float32", "data", [1.0, 5, False]),
    ("std_msgs/msg/Int8", "data", [0, 127, 128, -128, -129, 1.0, True, "1"]),
    ("std_msgs/msg/UInt8", "data", [0, 255, 256, -1, 3.0]),
    ("std_msgs/msg/Int64", "data", [2**63 - 1, 2**63, -(2**63), 1.5]),
    ("std_msgs/msg/UInt64", "data", [0, 2**64 - 1, -1, 1.0]),
    ("std_msgs/msg/Bool", "data", [True, False, 0, 1, "true", None]),
    ("std_msgs/msg/String", "data", ["", "x", 5, b"x", None]),
    (TWIST, "linear", [{"x": 1.0}, {"x": 1}, {"x": True}, {"w": 0.0}, {}, [1.0], 1.0]),
    (TWIST, None, [{}, {"linear": {"x": 2}}, {"linear": 1.0}, {"angular": {"z": "a"}},
                   {"linear": {"x": 1.0}, "extra": 1}]),
    ("geometry_msgs/msg/Pose", None, [{"position": {"x": 1.0}, "orientation": {"w": 1}},
                                      {"orientation": {"w": None}}]),
]


@pytest.mark.parametrize(("msg_type", "field", "values"), AGREEMENT,
                         ids=[f"{t.rsplit('/', 1)[1]}-{f}" for t, f, _ in AGREEMENT])
def test_write_check_agrees_with_the_server(msg_type: str, field: str | None,
                                            values: list[Any]) -> None:
    spec = InProcessBus().resolve(msg_type, field)
    assert spec.msg_type == msg_type
    server_check = value_converter(spec)
    channel = assert_write_check_agrees(spec, field, values)
    # What the client sends after converting passes the server unchanged in meaning.
    _stamps, sent = channel._ring.drain_stamped()
    assert server_check(list(sent)) == [server_check([v])[0] for v in sent]


def test_no_schema_checks_nothing() -> None:
    check = compile_check(None)
    assert check.coerce("anything") == "anything"
    odd = compile_check({"anyOf": [{"type": "number"}, {"type": "null"}]})
    assert odd.coerce(None) is None  # an unknown construct: the server decides


@pytest.mark.parametrize("schema", [
    {"$ref": "#/$defs/A", "$defs": {"A": {"$ref": "#/$defs/A"}}},  # a cycle
    {"type": "integer", "minimum": "0"},
    {"type": "array", "items": {"type": "number"}, "maxItems": 1.5},
    {"type": "object", "properties": {"x": "not a schema"}},
])
def test_a_schema_that_cannot_be_read_checks_nothing(schema: dict[str, Any]) -> None:
    assert compile_check(schema).coerce("x") == "x"


def test_numpy_scalars_are_plain_numbers() -> None:
    np = pytest.importorskip("numpy")
    check = compile_check({"type": "number"})
    assert type(check.coerce(np.float64(1.5))) is float
    assert type(check.coerce(np.int32(2))) is float
    assert compile_check({"type": "integer", "minimum": 0, "maximum": 255}).coerce(
        np.uint8(7)) == 7
