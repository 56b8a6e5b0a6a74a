"""ROS 2 message types bound at run time: names -> classes -> msgspec types and converters.

The ROS 1 bridge bound topics at run time with ``topic_tools::ShapeShifter``; ROS 2 has no such
class (thesis, section 3.2.2). It does not need one from Python: every generated message class
describes itself (``get_fields_and_field_types()`` and ``SLOT_TYPES``), which is enough to

* find the class from a name a client typed (``std_msgs/msg/Float64`` -> ``std_msgs.msg``),
* derive the msgspec type the server validates client values against (``ValueSpec``),
* build a ROS message from a plain value and read a plain value out of a ROS message.

All of that is computed once per type and field path and kept in a :class:`MessageCatalog`,
one per adapter (no module-level caches), so the per-value work is a few attribute accesses.

Mapping of ROS field types to channel values (plain Python, what crosses the adapter boundary):

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

This module imports no rclpy (only ``rosidl_parser.definition``, a pure-Python ROS package), so
it can be tested without a ROS context; :mod:`rlbridge.adapters.ros2` imports it.
"""

from __future__ import annotations

import importlib
import operator
import re
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Annotated, Any

import msgspec
from rosidl_parser import definition as idl

from rlbridge.adapters.base import BindingError, ValueSpec
from rlbridge.adapters.msgtypes import normalize_type_name, split_path

#: Plain value -> ROS field value (``None`` where the plain value is already what ROS wants).
_ToRos = Callable[[Any], Any] | None
#: ROS field value -> plain value (``None`` where ROS already gives plain Python).
_ToPlain = Callable[[Any], Any] | None
#: Validate and normalise a plain value for one field; raises ``ValueError`` with a reason.
_Check = Callable[[Any], Any]

_PACKAGE_RE = re.compile(r"[a-z][a-z0-9_]*\Z")
_TYPE_RE = re.compile(r"[A-Z][A-Za-z0-9]*\Z")

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


def pip_package(ros_package: str) -> str:
    """The PyPI wheel of a ROS package: ``sensor_msgs`` -> ``ros-sensor-msgs``."""
    return "ros-" + ros_package.replace("_", "-")


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


def _msgspec_checker(python_type: Any) -> _Check:
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


# -- codecs ------------------------------------------------------------------------------------


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
        for f in self.fields:
            if f.name == name:
                return f
        return None


@dataclass(frozen=True, slots=True)
class ChannelCodec:
    """What a publisher or subscription bound to (type, field path) needs per value."""

    spec: ValueSpec
    msg_cls: type[Any]
    #: Plain value -> fresh ROS message; raises :class:`BindingError` ``BAD_VALUE``.
    encode: Callable[[Any], Any]
    #: Received ROS message -> plain value of the bound field (or the whole message as a dict).
    decode: Callable[[Any], Any]


def _compile_from_struct(cls: type[Any], fields: Sequence[FieldCodec]) -> Callable[[Any], Any]:
    setters = tuple((f.name, f.to_ros) for f in fields)

    def from_struct(value: Any) -> Any:
        msg = cls()
        for name, to_ros in setters:
            v = getattr(value, name)
            setattr(msg, name, v if to_ros is None else to_ros(v))
        return msg

    return from_struct


def _compile_to_plain(fields: Sequence[FieldCodec]) -> Callable[[Any], dict[str, Any]]:
    getters = tuple((f.name, f.to_plain) for f in fields)

    def to_plain(msg: Any) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name, conv in getters:
            v = getattr(msg, name)
            out[name] = v if conv is None else conv(v)
        return out

    return to_plain


class MessageCatalog:
    """Message types resolved so far, by ROS 2 name; one per adapter, safe across threads.

    ``importer`` is ``importlib.import_module`` in production; tests pass their own to simulate
    missing packages without uninstalling anything.
    """

    def __init__(self, importer: Callable[[str], Any] = importlib.import_module) -> None:
        self._import = importer
        self._codecs: dict[str, MessageCodec] = {}
        self._lock = threading.RLock()

    # -- names -> classes

    def message_class(self, msg_type: str) -> tuple[str, type[Any]]:
        """``'std_msgs/msg/Float64'`` (or ``'std_msgs/Float64'``) -> (ROS 2 name, class)."""
        name = normalize_type_name(msg_type)
        package, _, type_name = name.split("/")
        if not (_PACKAGE_RE.match(package) and _TYPE_RE.match(type_name)):
            # Also keeps client-chosen strings from importing arbitrary modules.
            raise BindingError(
                "UNKNOWN_TYPE",
                f"'{msg_type}' is not a ROS 2 message type name: packages are lower_case, "
                "types CamelCase, e.g. 'std_msgs/msg/Float64'",
            )
        module_name = f"{package}.msg"
        try:
            module = self._import(module_name)
        except ModuleNotFoundError as exc:
            missing = (exc.name or package).split(".")[0]
            if exc.name == module_name:
                raise BindingError(
                    "UNKNOWN_TYPE", f"'{package}' is not a ROS 2 message package"
                ) from None
            raise BindingError(
                "PACKAGE_MISSING",
                f"message package '{missing}' (needed for {name}) is not installed; "
                f"install it with: pip install {pip_package(missing)}",
            ) from None
        cls: Any = getattr(module, type_name, None)
        if not _is_message_class(cls):
            known = sorted(n for n, v in vars(module).items() if _is_message_class(v))
            raise BindingError(
                "UNKNOWN_TYPE",
                f"unknown message type '{msg_type}'; {package} has: {', '.join(known)}",
            )
        return name, cls

    def codec(self, msg_type: str) -> MessageCodec:
        """The codec of a message type, built on first use."""
        name = normalize_type_name(msg_type)
        with self._lock:
            found = self._codecs.get(name)
            if found is None:
                found = self._codecs[name] = self._build(*self.message_class(name))
            return found

    # -- channels

    def resolve(self, msg_type: str, field: str | None) -> ValueSpec:
        """The channel's type and default; raises :class:`BindingError` for unusable bindings."""
        codec = self.codec(msg_type)
        if field is None:
            return ValueSpec(codec.name, None, codec.struct, codec.default)
        leaf = self._walk(codec, field)[-1]
        return ValueSpec(codec.name, field, leaf.python_type, leaf.default)

    def channel(self, msg_type: str, field: str | None) -> ChannelCodec:
        """Compile the per-value encode and decode functions of one binding."""
        codec = self.codec(msg_type)
        spec = self.resolve(msg_type, field)
        if field is None:
            return ChannelCodec(
                spec, codec.cls, _whole_encoder(codec), codec.to_plain
            )
        chain = self._walk(codec, field)
        return ChannelCodec(
            spec, codec.cls, _field_encoder(codec, chain), _field_decoder(chain)
        )

    def _walk(self, codec: MessageCodec, field: str) -> list[FieldCodec]:
        chain: list[FieldCodec] = []
        current: MessageCodec | None = codec
        for part in split_path(field):
            if current is None:
                raise BindingError(
                    "NO_SUCH_FIELD",
                    f"{codec.name} has no field '{field}': '{chain[-1].name}' is not a message",
                )
            found = current.field(part)
            if found is None:
                known = ", ".join(f.name for f in current.fields)
                raise BindingError(
                    "NO_SUCH_FIELD",
                    f"{codec.name} has no field '{field}' (fields of {current.name}: {known})",
                )
            chain.append(found)
            current = found.message
        return chain

    # -- classes -> codecs

    def _build(self, name: str, cls: type[Any]) -> MessageCodec:
        names = list(cls.get_fields_and_field_types())
        slot_types: Sequence[idl.AbstractType] = cls.SLOT_TYPES
        fresh = cls()
        fields = tuple(
            self._field(name, field_name, slot, getattr(fresh, field_name))
            for field_name, slot in zip(names, slot_types, strict=True)
        )
        struct_fields = [(f.name, f.python_type, _struct_default(f)) for f in fields]
        package, _, type_name = name.split("/")
        struct = msgspec.defstruct(
            type_name,
            struct_fields,
            module=f"{__name__}.{package}",
            forbid_unknown_fields=True,
        )
        to_plain = _compile_to_plain(fields)
        return MessageCodec(
            name=name,
            cls=cls,
            fields=fields,
            struct=struct,
            default=to_plain(fresh),
            from_struct=_compile_from_struct(cls, fields),
            to_plain=to_plain,
        )

    def _field(self, owner: str, name: str, slot: idl.AbstractType, ros_default: Any) -> FieldCodec:
        if isinstance(slot, idl.AbstractNestedType):
            return self._list_field(owner, name, slot, ros_default)
        python_type, check, to_ros, to_plain, message = self._leaf(owner, name, slot)
        default = ros_default if to_plain is None else to_plain(ros_default)
        return FieldCodec(name, python_type, default, check, to_ros, to_plain, message)

    def _leaf(
        self, owner: str, name: str, slot: idl.AbstractType
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
                return char, _msgspec_checker(char), None, None, None
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
            nested = self.codec("/".join(slot.namespaced_name()))
            return (
                nested.struct,
                _msgspec_checker(nested.struct),
                nested.from_struct,
                nested.to_plain,
                nested,
            )
        raise BindingError(
            "UNKNOWN_TYPE", f"{owner} field '{name}' has a type this bridge cannot map: {slot!r}"
        )

    def _list_field(
        self, owner: str, name: str, slot: idl.AbstractNestedType, ros_default: Any
    ) -> FieldCodec:
        item_type, _, item_to_ros, item_to_plain, _ = self._leaf(owner, name, slot.value_type)
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
            _msgspec_checker(python_type),
            to_ros,
            to_plain,
            None,
        )


def _is_message_class(obj: object) -> bool:
    return (
        isinstance(obj, type)
        and hasattr(obj, "SLOT_TYPES")
        and hasattr(obj, "get_fields_and_field_types")
        and hasattr(obj, "_TYPE_SUPPORT")
    )


def _int_to_octet(value: int) -> bytes:
    return bytes((value,))


def _octet_to_int(value: bytes) -> int:
    return value[0]


def _struct_default(f: FieldCodec) -> Any:
    """A msgspec default for ``f``: mutable defaults need a factory, messages their Struct."""
    if f.message is not None:
        return msgspec.field(default_factory=f.message.struct)
    if isinstance(f.default, list):
        if not f.default:
            return msgspec.field(default_factory=list)
        template, python_type = list(f.default), f.python_type
        return msgspec.field(default_factory=lambda: msgspec.convert(template, python_type))
    return f.default


def _whole_encoder(codec: MessageCodec) -> Callable[[Any], Any]:
    check = _msgspec_checker(codec.struct)
    from_struct = codec.from_struct
    name = codec.name

    def encode(value: Any) -> Any:
        try:
            struct = check(value)
        except ValueError as exc:
            raise BindingError("BAD_VALUE", f"not a {name}: {exc}") from None
        return from_struct(struct)

    return encode


def _field_encoder(codec: MessageCodec, chain: Sequence[FieldCodec]) -> Callable[[Any], Any]:
    """Plain value -> a fresh message with that one field set (the rest keep their defaults)."""
    cls = codec.cls
    leaf = chain[-1]
    check, to_ros, last = leaf.check, leaf.to_ros, leaf.name
    head = tuple(f.name for f in chain[:-1])
    where = f"{codec.name} field '{'.'.join((*head, last))}'"

    def value_for_ros(value: Any) -> Any:
        try:
            checked = check(value)
        except ValueError as exc:
            raise BindingError("BAD_VALUE", f"{where}: {exc}") from None
        return checked if to_ros is None else to_ros(checked)

    if not head:

        def encode_top(value: Any) -> Any:
            msg = cls()
            setattr(msg, last, value_for_ros(value))
            return msg

        return encode_top

    def encode_nested(value: Any) -> Any:
        msg = cls()
        target = msg
        for name in head:
            target = getattr(target, name)
        setattr(target, last, value_for_ros(value))
        return msg

    return encode_nested


def _field_decoder(chain: Sequence[FieldCodec]) -> Callable[[Any], Any]:
    get = operator.attrgetter(".".join(f.name for f in chain))
    to_plain = chain[-1].to_plain
    if to_plain is None:
        return get
    conv = to_plain

    def decode(msg: Any) -> Any:
        return conv(get(msg))

    return decode
