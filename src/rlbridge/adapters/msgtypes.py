"""ROS-shaped message types for middlewares that have no type system of their own.

The in-process bus needs the same names a ROS 2 user types (``std_msgs/msg/Float64``, field
``data``; ``geometry_msgs/msg/Twist``, field ``linear.x``), so channels written against the bus
move to ROS 2 unchanged. Each type is a ``msgspec.Struct`` with ROS defaults: decoding a value
into it *is* the validation, and ``msgspec.structs.fields`` gives field paths for free.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Annotated, Any

import msgspec

from rlbridge.adapters.base import BindingError, ValueSpec

I8 = Annotated[int, msgspec.Meta(ge=-(2**7), le=2**7 - 1)]
I16 = Annotated[int, msgspec.Meta(ge=-(2**15), le=2**15 - 1)]
I32 = Annotated[int, msgspec.Meta(ge=-(2**31), le=2**31 - 1)]
I64 = Annotated[int, msgspec.Meta(ge=-(2**63), le=2**63 - 1)]
U8 = Annotated[int, msgspec.Meta(ge=0, le=2**8 - 1)]
U16 = Annotated[int, msgspec.Meta(ge=0, le=2**16 - 1)]
U32 = Annotated[int, msgspec.Meta(ge=0, le=2**32 - 1)]
U64 = Annotated[int, msgspec.Meta(ge=0)]


_Struct = msgspec.Struct


class Bool(_Struct, forbid_unknown_fields=True):
    data: bool = False


class Int8(_Struct, forbid_unknown_fields=True):
    data: I8 = 0


class Int16(_Struct, forbid_unknown_fields=True):
    data: I16 = 0


class Int32(_Struct, forbid_unknown_fields=True):
    data: I32 = 0


class Int64(_Struct, forbid_unknown_fields=True):
    data: I64 = 0


class UInt8(_Struct, forbid_unknown_fields=True):
    data: U8 = 0


class UInt16(_Struct, forbid_unknown_fields=True):
    data: U16 = 0


class UInt32(_Struct, forbid_unknown_fields=True):
    data: U32 = 0


class UInt64(_Struct, forbid_unknown_fields=True):
    data: U64 = 0


class Float32(_Struct, forbid_unknown_fields=True):
    data: float = 0.0


class Float64(_Struct, forbid_unknown_fields=True):
    data: float = 0.0


class String(_Struct, forbid_unknown_fields=True):
    data: str = ""


class Point(_Struct, forbid_unknown_fields=True):
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


class Vector3(_Struct, forbid_unknown_fields=True):
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


class Quaternion(_Struct, forbid_unknown_fields=True):
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    w: float = 1.0


class Pose(_Struct, forbid_unknown_fields=True):
    position: Point = msgspec.field(default_factory=Point)
    orientation: Quaternion = msgspec.field(default_factory=Quaternion)


class Twist(_Struct, forbid_unknown_fields=True):
    linear: Vector3 = msgspec.field(default_factory=Vector3)
    angular: Vector3 = msgspec.field(default_factory=Vector3)


BUILTIN_TYPES: Mapping[str, type[msgspec.Struct]] = {
    **{
        f"std_msgs/msg/{cls.__name__}": cls
        for cls in (
            Bool, Int8, Int16, Int32, Int64, UInt8, UInt16, UInt32, UInt64,
            Float32, Float64, String,
        )
    },
    **{
        f"geometry_msgs/msg/{cls.__name__}": cls
        for cls in (Point, Vector3, Quaternion, Pose, Twist)
    },
}


def normalize_type_name(msg_type: str) -> str:
    """Accept ``pkg/msg/Name`` (ROS 2) and ``pkg/Name`` (ROS 1 habit); return the ROS 2 form."""
    parts = msg_type.strip().split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and parts[1] == "msg" and parts[0] and parts[2]:
        return msg_type.strip()
    raise BindingError(
        "UNKNOWN_TYPE",
        f"'{msg_type}' is not a message type name; expected 'package/msg/Type', "
        "e.g. 'std_msgs/msg/Float64'",
    )


def split_path(field: str) -> tuple[str, ...]:
    """``'linear.x'`` -> ``('linear', 'x')``; empty segments are a user error."""
    parts = tuple(field.split("."))
    if not all(parts):
        raise BindingError("NO_SUCH_FIELD", f"field path '{field}' has an empty segment")
    return parts


def resolve_struct_field(msg_type: str, cls: type[msgspec.Struct], field: str | None) -> ValueSpec:
    """Walk ``field`` through the struct ``cls``; the leaf's annotation is the channel's type."""
    if field is None:
        return ValueSpec(msg_type, None, cls, msgspec.to_builtins(cls()))
    current: Any = cls
    default: Any = cls()
    for name in split_path(field):
        if not (isinstance(current, type) and issubclass(current, msgspec.Struct)):
            raise BindingError(
                "NO_SUCH_FIELD", f"{msg_type} has no field '{field}': '{name}' is not in a message"
            )
        by_name = {f.name: f for f in msgspec.structs.fields(current)}
        if name not in by_name:
            known = ", ".join(sorted(by_name))
            raise BindingError(
                "NO_SUCH_FIELD", f"{msg_type} has no field '{field}' (fields here: {known})"
            )
        current = by_name[name].type
        default = getattr(default, name)
    builtin_default = msgspec.to_builtins(default)
    return ValueSpec(msg_type, field, current, builtin_default)


class TypeRegistry:
    """Message types by ROS 2 name; an instance per bus so tests can add types freely."""

    def __init__(self, types: Mapping[str, type[msgspec.Struct]] = BUILTIN_TYPES) -> None:
        self._types = dict(types)

    def register(self, name: str, cls: type[msgspec.Struct]) -> None:
        self._types[normalize_type_name(name)] = cls

    def names(self) -> list[str]:
        return sorted(self._types)

    def lookup(self, msg_type: str) -> tuple[str, type[msgspec.Struct]]:
        name = normalize_type_name(msg_type)
        cls = self._types.get(name)
        if cls is None:
            raise BindingError(
                "UNKNOWN_TYPE",
                f"unknown message type '{msg_type}'; this bus knows: {', '.join(self.names())}",
            )
        return name, cls

    def resolve(self, msg_type: str, field: str | None) -> ValueSpec:
        name, cls = self.lookup(msg_type)
        return resolve_struct_field(name, cls, field)


def get_path(message: Mapping[str, Any], path: tuple[str, ...]) -> Any:
    """Read a nested field of a message dict."""
    value: Any = message
    for name in path:
        value = value[name]
    return value


def with_path(template: Mapping[str, Any], path: tuple[str, ...], value: Any) -> dict[str, Any]:
    """A fresh message dict: ``template`` (the type's defaults) with one nested field set."""
    message = copy.deepcopy(dict(template))
    target = message
    for name in path[:-1]:
        target = target[name]
    target[path[-1]] = value
    return message
