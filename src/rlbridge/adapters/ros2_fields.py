"""ROS 2 message fields as channel values: the type a field maps to, its check, its converters.

One field of a generated message class is described by its IDL slot type (``SLOT_TYPES``); this
module maps that to what crosses the adapter boundary, plain Python, with the msgspec type the
server validates values against (``ValueSpec``) and a per-value check cheaper than
``msgspec.convert`` where there is one:

===========================  ==========================================================
ROS (IDL)                    channel value / msgspec type
===========================  ==========================================================
int8 .. uint64               ``int`` with its range (``Annotated[int, Meta(ge, le)]``)
float, double                ``float`` (ints are accepted and widened, bools are not)
boolean                      ``bool``
octet (``byte``)             ``int`` in 0..255 (ROS uses 1-byte ``bytes``; ints survive JSON
                             and msgpack alike, base64 strings would not)
char, wchar                  ``str`` of length 1
string, wstring              ``str`` (``max_length`` when bounded)
nested message               a ``msgspec.Struct`` (plain ``dict`` on the wire)
T[N], sequence<T>[, N]       ``list[T]`` with its length limits
===========================  ==========================================================

A message is its fields (:class:`MessageCodec`, a nested field holds one), so both live here;
:mod:`.ros2_codecs` builds them and compiles the per-value converters, importing this module,
never the other way round.

Like :mod:`.ros2_types`, this module imports no rclpy, only ``rosidl_parser.definition``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Annotated, Any

import msgspec
from rosidl_parser import definition as idl

from rlbridge.adapters.base import BindingError

#: Plain value -> ROS field value (``None`` where the plain value is already what ROS wants).
_ToRos = Callable[[Any], Any] | None
#: ROS field value -> plain value (``None`` where ROS already gives plain Python).
_ToPlain = Callable[[Any], Any] | None
#: Validate and normalise a plain value for one field; raises ``ValueError`` with a reason.
_Check = Callable[[Any], Any]
#: The codec of a nested message type, by ROS 2 name (the catalog's, which caches them).
Nested = Callable[[str], "MessageCodec"]

_INT_RANGES: Mapping[str, tuple[int, int]] = {
    "int8": (-(2**7), 2**7 - 1),
    "int16": (-(2**15), 2**15 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "int64": (-(2**63), 2**63 - 1),
    "uint8": (0, 2**8 - 1),
    "uint16": (0, 2**16 - 1),
    "uint32": (0, 2**32 - 1),
    "uint64": (0, 2**64 - 1),
    # IDL spellings that .msg files never produce but .idl files may.
    "short": (-(2**15), 2**15 - 1),
    "long": (-(2**31), 2**31 - 1),
    "long long": (-(2**63), 2**63 - 1),
    "unsigned short": (0, 2**16 - 1),
    "unsigned long": (0, 2**32 - 1),
    "unsigned long long": (0, 2**64 - 1),
    "octet": (0, 2**8 - 1),
}
_INT64_MAX = 2**63 - 1
_FLOATS = frozenset({"float", "double", "long double"})
_CHARS = frozenset({"char", "wchar"})


# -- validation of single values (cheaper than msgspec.convert on an Annotated scalar) --------


def _check_float(value: Any) -> float:
    if isinstance(value, float):
        return value
    if isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    raise ValueError(f"expected a float, got {type(value).__name__} {value!r}")


def _check_bool(value: Any) -> bool:
    if isinstance(value, bool):
        return value
    raise ValueError(f"expected a bool, got {type(value).__name__} {value!r}")


def _int_checker(low: int, high: int) -> _Check:
    def check(value: Any) -> int:
        if isinstance(value, int) and not isinstance(value, bool) and low <= value <= high:
            return value
        raise ValueError(f"expected an int in [{low}, {high}], got {value!r}")

    return check


def _str_checker(max_length: int | None) -> _Check:
    def check(value: Any) -> str:
        if isinstance(value, str) and (max_length is None or len(value) <= max_length):
            return value
        limit = "" if max_length is None else f" of at most {max_length} characters"
        raise ValueError(f"expected a string{limit}, got {value!r}")

    return check


def msgspec_checker(python_type: Any) -> _Check:
    """For lists and nested messages: one ``msgspec.convert`` does the whole tree."""

    def check(value: Any) -> Any:
        if isinstance(value, msgspec.Struct) and type(value) is not python_type:
            value = msgspec.to_builtins(value)
        try:
            return msgspec.convert(value, python_type)
        except msgspec.ValidationError as exc:
            raise ValueError(str(exc)) from None

    return check


def _int_meta(low: int, high: int) -> msgspec.Meta:
    """Range constraints for msgspec, which cannot express bounds beyond int64 (uint64's top):
    those values pass msgspec and are refused by the adapter's own check at publish time."""
    if high > _INT64_MAX:
        return msgspec.Meta(ge=low)
    return msgspec.Meta(ge=low, le=high)


def _to_list(value: Any) -> list[Any]:
    """ROS numeric arrays are ``array.array`` or ``numpy.ndarray``; both have ``tolist``."""
    tolist = getattr(value, "tolist", None)
    return list(value) if tolist is None else list(tolist())


def _int_to_octet(value: int) -> bytes:
    return bytes((value,))


def _octet_to_int(value: bytes) -> int:
    return value[0]


@dataclass(frozen=True, slots=True)
class FieldCodec:
    """One field of a message type: its channel type, default and converters."""

    name: str
    python_type: Any
    default: Any
    check: _Check
    to_ros: _ToRos
    to_plain: _ToPlain
    message: MessageCodec | None  # set when the field is a nested message


@dataclass(frozen=True, slots=True)
class MessageCodec:
    """A message class with everything needed to move it to and from plain Python."""

    name: str
    cls: type[Any]
    fields: tuple[FieldCodec, ...]
    struct: type[msgspec.Struct]
    default: dict[str, Any]
    from_struct: Callable[[Any], Any]
    to_plain: Callable[[Any], dict[str, Any]]

    def field(self, name: str) -> FieldCodec | None:
        """The field called ``name``, or None (the caller names the fields there are)."""
        for f in self.fields:
            if f.name == name:
                return f
        return None


def field_codec(
    owner: str, name: str, slot: idl.AbstractType, ros_default: Any, nested: Nested
) -> FieldCodec:
    """The codec of field ``name`` of message type ``owner``; ``nested`` builds sub-messages."""
    if isinstance(slot, idl.AbstractNestedType):
        return _list_field(owner, name, slot, ros_default, nested)
    python_type, check, to_ros, to_plain, message = _leaf(owner, name, slot, nested)
    default = ros_default if to_plain is None else to_plain(ros_default)
    return FieldCodec(name, python_type, default, check, to_ros, to_plain, message)


def _leaf(
    owner: str, name: str, slot: idl.AbstractType, nested: Nested
) -> tuple[Any, _Check, _ToRos, _ToPlain, MessageCodec | None]:
    """The channel type and converters of a non-list field."""
    if isinstance(slot, idl.BasicType):
        kind = slot.typename
        if kind in _FLOATS:
            return float, _check_float, None, None, None
        if kind == "boolean":
            return bool, _check_bool, None, None, None
        if kind in _CHARS:
            char = Annotated[str, msgspec.Meta(min_length=1, max_length=1)]
            return char, msgspec_checker(char), None, None, None
        low, high = _INT_RANGES[kind]
        ranged = Annotated[int, _int_meta(low, high)]
        if kind == "octet":
            return ranged, _int_checker(low, high), _int_to_octet, _octet_to_int, None
        return ranged, _int_checker(low, high), None, None, None
    if isinstance(slot, idl.AbstractGenericString):
        limit: int | None = None
        text: Any = str
        if isinstance(slot, idl.BoundedString | idl.BoundedWString):
            limit = int(slot.maximum_size)
            text = Annotated[str, msgspec.Meta(max_length=limit)]
        return text, _str_checker(limit), None, None, None
    if isinstance(slot, idl.NamespacedType):
        message = nested("/".join(slot.namespaced_name()))
        return (
            message.struct,
            msgspec_checker(message.struct),
            message.from_struct,
            message.to_plain,
            message,
        )
    raise BindingError(
        "UNKNOWN_TYPE", f"{owner} field '{name}' has a type this bridge cannot map: {slot!r}"
    )


def _list_field(
    owner: str, name: str, slot: idl.AbstractNestedType, ros_default: Any, nested: Nested
) -> FieldCodec:
    item_type, _, item_to_ros, item_to_plain, _ = _leaf(owner, name, slot.value_type, nested)
    meta: msgspec.Meta | None = None
    if isinstance(slot, idl.Array):
        meta = msgspec.Meta(min_length=slot.size, max_length=slot.size)
    elif isinstance(slot, idl.BoundedSequence):
        meta = msgspec.Meta(max_length=slot.maximum_size)
    python_type: Any = list[item_type]  # type: ignore[valid-type]
    if meta is not None:
        python_type = Annotated[python_type, meta]
    to_ros: _ToRos = None
    if item_to_ros is not None:
        conv_in = item_to_ros

        def to_ros(values: Any) -> list[Any]:
            return [conv_in(v) for v in values]

    if item_to_plain is None:
        to_plain: Callable[[Any], Any] = _to_list
    else:
        conv_out = item_to_plain

        def to_plain(values: Any) -> list[Any]:
            return [conv_out(v) for v in values]

    return FieldCodec(
        name,
        python_type,
        to_plain(ros_default),
        msgspec_checker(python_type),
        to_ros,
        to_plain,
        None,
    )
