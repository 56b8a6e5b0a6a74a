"""Compiled per-value conversion of one binding: plain value -> ROS message -> plain value.

A message codec and a channel codec are built once per type and field path; what runs per value
is a closure over the field names and converters, so publishing or delivering a value costs a
few attribute accesses, not a walk over the message description.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import msgspec

from rlbridge.adapters.base import BindingError, ValueSpec
from rlbridge.adapters.ros2_fields import FieldCodec, MessageCodec, msgspec_checker


@dataclass(frozen=True, slots=True)
class ChannelCodec:
    """What a publisher or subscription bound to (type, field path) needs per value."""

    spec: ValueSpec
    msg_cls: type[Any]
    #: Plain value -> fresh ROS message; raises :class:`BindingError` ``BAD_VALUE``.
    encode: Callable[[Any], Any]
    #: Received ROS message -> plain value of the bound field (or the whole message as a dict).
    decode: Callable[[Any], Any]


def compile_from_struct(cls: type[Any], fields: Sequence[FieldCodec]) -> Callable[[Any], Any]:
    """A validated Struct -> a fresh ``cls`` message, field by field."""
    setters = tuple((f.name, f.to_ros) for f in fields)

    def from_struct(value: Any) -> Any:
        msg = cls()
        for name, to_ros in setters:
            v = getattr(value, name)
            setattr(msg, name, v if to_ros is None else to_ros(v))
        return msg

    return from_struct


def compile_to_plain(fields: Sequence[FieldCodec]) -> Callable[[Any], dict[str, Any]]:
    """A ROS message -> a dict of plain values (what a whole-message channel delivers)."""
    getters = tuple((f.name, f.to_plain) for f in fields)

    def to_plain(msg: Any) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name, conv in getters:
            v = getattr(msg, name)
            out[name] = v if conv is None else conv(v)
        return out

    return to_plain


def struct_default(f: FieldCodec) -> Any:
    """A msgspec default for ``f``: mutable defaults need a factory, messages their Struct."""
    if f.message is not None:
        return msgspec.field(default_factory=f.message.struct)
    if isinstance(f.default, list):
        if not f.default:
            return msgspec.field(default_factory=list)
        template, python_type = list(f.default), f.python_type
        return msgspec.field(default_factory=lambda: msgspec.convert(template, python_type))
    return f.default


def whole_encoder(codec: MessageCodec) -> Callable[[Any], Any]:
    """Plain value (a dict or the Struct) -> a fresh message; a bad value is ``BAD_VALUE``."""
    check = msgspec_checker(codec.struct)
    from_struct = codec.from_struct
    name = codec.name

    def encode(value: Any) -> Any:
        try:
            struct = check(value)
        except ValueError as exc:
            raise BindingError("BAD_VALUE", f"not a {name}: {exc}") from None
        return from_struct(struct)

    return encode


def field_encoder(codec: MessageCodec, chain: Sequence[FieldCodec]) -> Callable[[Any], Any]:
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


def field_decoder(chain: Sequence[FieldCodec]) -> Callable[[Any], Any]:
    """A received message -> the plain value at the end of ``chain`` (one ``attrgetter``)."""
    get = operator.attrgetter(".".join(f.name for f in chain))
    to_plain = chain[-1].to_plain
    if to_plain is None:
        return get
    conv = to_plain

    def decode(msg: Any) -> Any:
        return conv(get(msg))

    return decode
