"""Run-time ROS 2 type resolution and conversion (:mod:`rlbridge.adapters.ros2_types`).

No rclpy context is needed here: only the generated message classes, so these run fast and
can sweep every installed std_msgs and geometry_msgs type.
"""

from __future__ import annotations

import importlib
import math
from typing import Any

import msgspec
import pytest
from hypothesis import given
from hypothesis import strategies as st

pytest.importorskip(
    "rosidl_parser",
    reason="ROS 2 message packages are not installed (pip install 'rlbridge-sdk[ros2]')",
)

from rlbridge.adapters.base import BindingError
from rlbridge.adapters.ros2_types import MessageCatalog, pip_package

pytestmark = pytest.mark.ros2

INT_TYPES = {
    "Int8": (-(2**7), 2**7 - 1),
    "Int16": (-(2**15), 2**15 - 1),
    "Int32": (-(2**31), 2**31 - 1),
    "Int64": (-(2**63), 2**63 - 1),
    "UInt8": (0, 2**8 - 1),
    "UInt16": (0, 2**16 - 1),
    "UInt32": (0, 2**32 - 1),
    "UInt64": (0, 2**64 - 1),
}


def _all_types(package: str) -> list[str]:
    module = importlib.import_module(f"{package}.msg")
    return sorted(
        f"{package}/msg/{name}"
        for name, cls in vars(module).items()
        if isinstance(cls, type) and hasattr(cls, "SLOT_TYPES")
    )


ALL_TYPES = _all_types("std_msgs") + _all_types("geometry_msgs")


@pytest.fixture(scope="module")
def catalog() -> MessageCatalog:
    return MessageCatalog()


@pytest.mark.parametrize("msg_type", ALL_TYPES)
def test_every_installed_type_round_trips_its_default(
    catalog: MessageCatalog, msg_type: str
) -> None:
    spec = catalog.resolve(msg_type, None)
    channel = catalog.channel(msg_type, None)
    # The default is plain Python that survives the server's validation unchanged...
    assert msgspec.to_builtins(msgspec.convert(spec.default, spec.python_type)) == spec.default
    assert msgspec.json.decode(msgspec.json.encode(spec.default)) == spec.default
    # ...and a message built from it reads back as the same value.
    assert channel.decode(channel.encode(spec.default)) == spec.default
    assert channel.decode(channel.msg_cls()) == spec.default


@pytest.mark.parametrize("name", sorted(INT_TYPES))
def test_integer_ranges(catalog: MessageCatalog, name: str) -> None:
    low, high = INT_TYPES[name]
    msg_type = f"std_msgs/msg/{name}"
    spec = catalog.resolve(msg_type, "data")
    channel = catalog.channel(msg_type, "data")
    for good in (low, high, 0):
        assert msgspec.convert(good, spec.python_type) == good
        assert channel.decode(channel.encode(good)) == good
    for bad in (low - 1, high + 1):
        if bad < 2**63:  # msgspec cannot bound beyond int64; the adapter's check still does
            with pytest.raises(msgspec.ValidationError):
                msgspec.convert(bad, spec.python_type)
        with pytest.raises(BindingError) as info:
            channel.encode(bad)
        assert info.value.code == "BAD_VALUE"
        assert str(low) in info.value.reason
        assert str(high) in info.value.reason


@given(st.integers(-(2**63), 2**63 - 1), st.floats(allow_nan=False))
def test_values_round_trip(value: int, number: float) -> None:
    catalog = MessageCatalog()
    i64 = catalog.channel("std_msgs/msg/Int64", "data")
    assert i64.decode(i64.encode(value)) == value
    f64 = catalog.channel("std_msgs/msg/Float64", "data")
    assert f64.decode(f64.encode(number)) == number
    f32 = catalog.channel("std_msgs/msg/Float32", "data")
    back = f32.decode(f32.encode(number))
    assert type(back) is float
    if abs(number) < 3.4e38:
        assert math.isclose(back, number, rel_tol=1e-6, abs_tol=1e-37)


@given(st.text())
def test_strings_round_trip(text: str) -> None:
    channel = MessageCatalog().channel("std_msgs/msg/String", "data")
    assert channel.decode(channel.encode(text)) == text


def test_channel_values_are_plain_python(catalog: MessageCatalog) -> None:
    """No numpy arrays, array.array or bytes leak out: the server encodes with msgspec."""
    channel = catalog.channel("geometry_msgs/msg/PoseWithCovariance", None)
    value = channel.decode(channel.encode({"covariance": [1.0] * 36}))
    assert type(value["covariance"]) is list
    assert all(type(v) is float for v in value["covariance"])
    multi = catalog.channel("std_msgs/msg/UInt8MultiArray", "data")
    assert multi.decode(multi.encode([1, 2, 255])) == [1, 2, 255]
    octets = catalog.channel("std_msgs/msg/ByteMultiArray", "data")
    assert octets.decode(octets.encode([0, 128, 255])) == [0, 128, 255]
    byte = catalog.channel("std_msgs/msg/Byte", "data")
    assert byte.decode(byte.encode(200)) == 200


def test_fixed_arrays_need_their_length(catalog: MessageCatalog) -> None:
    channel = catalog.channel("geometry_msgs/msg/PoseWithCovariance", "covariance")
    assert channel.spec.default == [0.0] * 36
    for bad in ([0.0] * 35, [0.0] * 37, ["x"] * 36):
        with pytest.raises(BindingError) as info:
            channel.encode(bad)
        assert info.value.code == "BAD_VALUE"


def test_sequences_of_messages(catalog: MessageCatalog) -> None:
    channel = catalog.channel("geometry_msgs/msg/Polygon", None)
    points = [{"x": 1.0, "y": 2.0, "z": 3.0}, {"x": -1.0, "y": 0.0, "z": 0.5}]
    assert channel.decode(channel.encode({"points": points})) == {"points": points}
    with pytest.raises(BindingError):
        channel.encode({"points": [{"x": 1.0, "q": 2.0}]})


def test_struct_defaults_are_fresh(catalog: MessageCatalog) -> None:
    struct = catalog.resolve("geometry_msgs/msg/PoseWithCovariance", None).python_type
    first, second = struct(), struct()
    first.covariance[0] = 99.0
    first.pose.position.x = 5.0
    assert second.covariance[0] == 0.0
    assert second.pose.position.x == 0.0


def test_field_spec_and_nested_message_field(catalog: MessageCatalog) -> None:
    spec = catalog.resolve("geometry_msgs/msg/Twist", "linear")
    assert spec.default == {"x": 0.0, "y": 0.0, "z": 0.0}
    channel = catalog.channel("geometry_msgs/msg/Twist", "linear")
    assert channel.decode(channel.encode({"x": 2})) == {"x": 2.0, "y": 0.0, "z": 0.0}
    header = catalog.resolve("std_msgs/msg/Header", "stamp.nanosec")
    assert msgspec.convert(999_999_999, header.python_type) == 999_999_999
    with pytest.raises(msgspec.ValidationError):
        msgspec.convert(-1, header.python_type)


@pytest.mark.parametrize(
    ("name", "code"),
    [
        ("os/msg/Path", "UNKNOWN_TYPE"),  # a Python package, not a message package
        ("std_msgs/msg/float64", "UNKNOWN_TYPE"),  # type names are CamelCase
        ("Std_msgs/msg/Float64", "UNKNOWN_TYPE"),  # package names are lower_case
        ("std_msgs/srv/Float64", "UNKNOWN_TYPE"),
        ("../x/msg/Y", "UNKNOWN_TYPE"),
        ("std_msgs/msg/Float64MultiArray", None),
    ],
)
def test_names_that_are_refused_before_any_import(
    catalog: MessageCatalog, name: str, code: str | None
) -> None:
    if code is None:
        catalog.resolve(name, None)
        return
    with pytest.raises(BindingError) as info:
        catalog.resolve(name, None)
    assert info.value.code == code


def test_unknown_type_lists_what_the_package_has(catalog: MessageCatalog) -> None:
    with pytest.raises(BindingError) as info:
        catalog.resolve("geometry_msgs/msg/Twister", None)
    assert info.value.code == "UNKNOWN_TYPE"
    assert "Twist" in info.value.reason
    assert "TwistStamped" in info.value.reason


def test_missing_dependency_package_is_named() -> None:
    """A message whose nested type lives in an uninstalled package names that package."""

    def importer(name: str) -> Any:
        if name == "builtin_interfaces.msg":
            raise ModuleNotFoundError("No module named 'builtin_interfaces'",
                                      name="builtin_interfaces")
        return importlib.import_module(name)

    with pytest.raises(BindingError) as info:
        MessageCatalog(importer).resolve("std_msgs/msg/Header", None)
    assert info.value.code == "PACKAGE_MISSING"
    assert "builtin_interfaces" in info.value.reason
    assert "pip install ros-builtin-interfaces" in info.value.reason


def test_pip_package_names() -> None:
    assert pip_package("sensor_msgs") == "ros-sensor-msgs"
    assert pip_package("geometry_msgs") == "ros-geometry-msgs"
