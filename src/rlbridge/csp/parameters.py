"""ROS 2 parameters as plain Python values, through the parameter services every node has.

A ROS 2 node serves ``<node>/get_parameters``, ``<node>/set_parameters`` and
``<node>/list_parameters`` (``rcl_interfaces``); ``ros2 param`` uses them, and so does the
SDK, through ordinary service calls (:meth:`Bridge.call`), so the server needs nothing of its
own for parameters. This module converts between Python values and
``rcl_interfaces/msg/ParameterValue`` dicts (a type tag and one field per type).
"""

from __future__ import annotations

from typing import Any

from rlbridge.errors import ParameterError

GET = "rcl_interfaces/srv/GetParameters"
SET = "rcl_interfaces/srv/SetParameters"
LIST = "rcl_interfaces/srv/ListParameters"

#: ``ParameterType`` constants of rcl_interfaces, and the ParameterValue field of each.
_FIELDS = {1: "bool_value", 2: "integer_value", 3: "double_value", 4: "string_value",
           5: "byte_array_value", 6: "bool_array_value", 7: "integer_array_value",
           8: "double_array_value", 9: "string_array_value"}

ParameterValue = bool | int | float | str | bytes | list[bool] | list[int] | list[float] | list[str]


def node_service(node: str, name: str) -> str:
    """``'talker'`` or ``'/ns/talker'`` -> the node's parameter service ``/ns/talker/<name>``."""
    node = node.strip().rstrip("/")
    return f"{node if node.startswith('/') else '/' + node}/{name}"


def to_ros(value: Any) -> dict[str, Any]:
    """A Python value -> a ParameterValue dict; ``ParameterError`` for a type ROS lacks."""
    if isinstance(value, bool):
        return {"type": 1, "bool_value": value}
    if isinstance(value, int):
        return {"type": 2, "integer_value": value}
    if isinstance(value, float):
        return {"type": 3, "double_value": value}
    if isinstance(value, str):
        return {"type": 4, "string_value": value}
    if isinstance(value, bytes | bytearray):
        return {"type": 5, "byte_array_value": list(value)}
    if isinstance(value, list | tuple) and value:
        for kind, code in ((bool, 6), (int, 7), (float, 8), (str, 9)):
            if all(type(v) is kind for v in value):
                return {"type": code, _FIELDS[code]: list(value)}
        if all(type(v) in (int, float) for v in value):
            return {"type": 8, "double_array_value": [float(v) for v in value]}
    raise ParameterError(f"{value!r} has no ROS 2 parameter type (bool, int, float, str, "
                         "bytes, or a non-empty list of one of bool, int, float, str)")


def from_ros(value: dict[str, Any]) -> ParameterValue | None:
    """A ParameterValue dict -> the Python value (``None`` for ``PARAMETER_NOT_SET``)."""
    field = _FIELDS.get(int(value.get("type", 0)))
    if field is None:
        return None
    got = value.get(field)
    if field == "byte_array_value":
        return bytes(b if isinstance(b, int) else ord(b) for b in got or [])
    return list(got) if isinstance(got, list | tuple) else got
