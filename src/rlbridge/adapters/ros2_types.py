"""ROS 2 message types bound at run time: names -> classes -> msgspec types and converters.

The ROS 1 bridge bound topics at run time with ``topic_tools::ShapeShifter``; ROS 2 has no such


class (thesis, section 3.2.2). It does not need one from Python: every generated message class
describes itself (``get_fields_and_field_types()`` and ``SLOT_TYPES``), which is enough to

* find the class from a name a client typed (``std_msgs/msg/Float64`` -> ``std_msgs.msg``),
* derive the msgspec type the server validates client values against (``ValueSpec``),
* build a ROS message from a plain value and read a plain value out of a ROS message.

All of that is computed once per type and field path and kept in a :class:`MessageCatalog`,
one per adapter (no module-level caches), so the per-value work is a few attribute accesses.

The mapping of ROS field types to channel values is in :mod:`.ros2_fields`; the compiled
per-value conversions in :mod:`.ros2_codecs`. This module finds classes by name and caches what
is built for them.

This module imports no rclpy (only ``rosidl_parser.definition``, a pure-Python ROS package), so
it can be tested without a ROS context; :mod:`rlbridge.adapters.ros2` imports it.
"""

from __future__ import annotations

import importlib
import re
import threading
from collections.abc import Callable, Sequence
from typing import Any

import msgspec
from rosidl_parser import definition as idl

from rlbridge.adapters.base import BindingError, ValueSpec
from rlbridge.adapters.msgtypes import normalize_type_name, split_path
from rlbridge.adapters.ros2_codecs import (
    ChannelCodec,
    compile_from_struct,
    compile_to_plain,
    field_decoder,
    field_encoder,
    struct_default,
    whole_encoder,
)
from rlbridge.adapters.ros2_fields import FieldCodec, MessageCodec, field_codec

__all__ = ["MessageCatalog", "pip_package"]

_PACKAGE_RE = re.compile(r"[a-z][a-z0-9_]*\Z")
_TYPE_RE = re.compile(r"[A-Z][A-Za-z0-9]*\Z")


def pip_package(ros_package: str) -> str:
    """The PyPI wheel of a ROS package: ``sensor_msgs`` -> ``ros-sensor-msgs``."""
    return "ros-" + ros_package.replace("_", "-")


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

    def class_codec(self, name: str, cls: type[Any]) -> MessageCodec:
        """The codec of a message class found another way (a service's request or response,
        an action's goal), cached under ``name`` like the types found by name."""
        with self._lock:
            found = self._codecs.get(name)
            if found is None:
                found = self._codecs[name] = self._build(name, cls)
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
                spec, codec.cls, whole_encoder(codec), codec.to_plain
            )
        chain = self._walk(codec, field)
        return ChannelCodec(
            spec, codec.cls, field_encoder(codec, chain), field_decoder(chain)
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
            field_codec(name, field_name, slot, getattr(fresh, field_name), self.codec)
            for field_name, slot in zip(names, slot_types, strict=True)
        )
        struct_fields = [(f.name, f.python_type, struct_default(f)) for f in fields]
        package, _, type_name = name.split("/")
        struct = msgspec.defstruct(
            type_name,
            struct_fields,
            module=f"{__name__}.{package}",
            forbid_unknown_fields=True,
        )
        to_plain = compile_to_plain(fields)
        return MessageCodec(
            name=name,
            cls=cls,
            fields=fields,
            struct=struct,
            default=to_plain(fresh),
            from_struct=compile_from_struct(cls, fields),
            to_plain=to_plain,
        )


def _is_message_class(obj: object) -> bool:
    return (
        isinstance(obj, type)
        and hasattr(obj, "SLOT_TYPES")
        and hasattr(obj, "get_fields_and_field_types")
        and hasattr(obj, "_TYPE_SUPPORT")
    )
