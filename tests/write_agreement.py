"""The SDK's write-time check against the server's own, value by value (tests/client and
tests/adapters run it on the in-process bus's and the ROS 2 adapter's message types).

A plain module (``from write_agreement import ...``), not a fixture: the check is a function of
a resolved type and some values.
"""

from __future__ import annotations

from typing import Any

import msgspec

from rlbridge import WrongValueType
from rlbridge.adapters.base import ValueSpec
from rlbridge.csp.bridge_channels import OutgoingChannel
from rlbridge.csp.channel import Doorbell
from rlbridge.server.admission import value_converter, value_schema
from rlbridge.wire import TopicAck


def assert_write_check_agrees(spec: ValueSpec, field: str | None,
                              values: list[Any]) -> OutgoingChannel:
    """For each value, ``write`` on a channel bound with ``spec``'s schema refuses it exactly
    when the server's converter does. Returns the channel (what it accepted is in its ring)."""
    server_check = value_converter(spec)
    channel = OutgoingChannel(1, "/agree", spec.msg_type, field, transport="tcp",
                              immediate=False, buffer_size=64, doorbell=Doorbell())
    channel.bound(TopicAck(1, spec.msg_type, spec.default, value_schema(spec)))
    for value in values:
        try:
            server_check([value])
        except msgspec.ValidationError:
            server_ok = False
        else:
            server_ok = True
        try:
            channel.write(value)
        except WrongValueType:
            client_ok = False
        else:
            client_ok = True
        assert client_ok == server_ok, f"{value!r}: client {client_ok}, server {server_ok}"
    return channel
