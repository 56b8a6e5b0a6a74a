"""Services on the in-process bus: a table of providers, calls that wait for their answer.

The bus has no ROS, so it knows the service types below (ROS names, ROS defaults, msgspec
Structs as in :mod:`.msgtypes`) and lets tests register more. A call validates the request,
finds the provider, hands it the request and a :class:`WaitingReply`, and waits on it: the
provider (a client of the bridge, through the server) may answer from any thread, later.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import msgspec

from rlbridge.adapters.base import BindingError, ServiceHandler

_Struct = msgspec.Struct


class _Empty(_Struct, forbid_unknown_fields=True):
    pass


class _SetBoolRequest(_Struct, forbid_unknown_fields=True):
    data: bool = False


class _Outcome(_Struct, forbid_unknown_fields=True):
    success: bool = False
    message: str = ""


@dataclass(frozen=True, slots=True)
class ServiceType:
    """A service type: its request and response as Structs (validation is decoding)."""

    name: str
    request: type[msgspec.Struct]
    response: type[msgspec.Struct]


BUILTIN_SERVICES: Mapping[str, ServiceType] = {
    t.name: t
    for t in (
        ServiceType("std_srvs/srv/Empty", _Empty, _Empty),
        ServiceType("std_srvs/srv/Trigger", _Empty, _Outcome),
        ServiceType("std_srvs/srv/SetBool", _SetBoolRequest, _Outcome),
    )
}


def normalize_service_type(srv_type: str) -> str:
    """``pkg/srv/Name`` or ``pkg/Name`` -> ``pkg/srv/Name``; anything else is UNKNOWN_TYPE."""
    parts = srv_type.strip().split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/srv/{parts[1]}"
    if len(parts) == 3 and parts[1] == "srv" and parts[0] and parts[2]:
        return srv_type.strip()
    raise BindingError(
        "UNKNOWN_TYPE",
        f"'{srv_type}' is not a service type name; expected 'package/srv/Type', "
        "e.g. 'std_srvs/srv/SetBool'",
    )


def check_service_name(service: str) -> None:
    """Service names follow the topic name rules (ROS 2 checks them the same way)."""
    ok = (
        len(service) > 1
        and service.startswith("/")
        and not service.endswith("/")
        and "//" not in service
        and all(c.isalnum() or c in "/_" for c in service)
        and not any(part[:1].isdigit() for part in service.split("/"))
    )
    if not ok:
        raise BindingError(
            "BAD_TOPIC",
            f"'{service}' is not a valid service name: use '/name' with letters, digits, "
            "'_' and '/', no empty or digit-leading parts",
        )


class WaitingReply:
    """A :class:`~rlbridge.adapters.base.ServiceReply` that a calling thread waits on."""

    def __init__(self, stype: ServiceType) -> None:
        self._type = stype
        self._done = threading.Event()
        self._lock = threading.Lock()
        self.response: dict[str, Any] | None = None
        self.failure: str | None = None

    def send(self, response: dict[str, Any]) -> None:
        try:
            checked = msgspec.convert(response, self._type.response)
        except msgspec.ValidationError as exc:
            raise BindingError(
                "BAD_VALUE", f"not a {self._type.name} response: {exc}") from None
        with self._lock:
            if not self._done.is_set():
                self.response = msgspec.to_builtins(checked)
                self._done.set()

    def fail(self, reason: str) -> None:
        with self._lock:
            if not self._done.is_set():
                self.failure = reason
                self._done.set()

    def wait(self, timeout: float) -> bool:
        return self._done.wait(timeout)


@dataclass(eq=False)
class _Provider:
    name: str
    stype: ServiceType
    handler: ServiceHandler
    table: InProcessServices

    def close(self) -> None:
        self.table.remove(self)


class InProcessServices:
    """The bus's services: one provider per name, typed; see the module docstring."""

    def __init__(self, types: Mapping[str, ServiceType] = BUILTIN_SERVICES) -> None:
        self._types = dict(types)
        self._providers: dict[str, _Provider] = {}
        self._lock = threading.Lock()

    def register_type(self, stype: ServiceType) -> None:
        self._types[normalize_service_type(stype.name)] = stype

    def service_type(self, srv_type: str) -> ServiceType:
        name = normalize_service_type(srv_type)
        found = self._types.get(name)
        if found is None and name.startswith("rcl_interfaces/"):
            raise BindingError("UNKNOWN_TYPE", f"the in-process bus has no ROS nodes and no "
                               f"parameters ({name}); serve with --adapter ros2")
        if found is None:
            raise BindingError(
                "UNKNOWN_TYPE",
                f"unknown service type '{srv_type}'; this bus knows: "
                f"{', '.join(sorted(self._types))}")
        return found

    def call(self, service: str, srv_type: str, request: dict[str, Any],
             timeout: float) -> dict[str, Any]:
        stype = self.service_type(srv_type)
        check_service_name(service)
        try:
            checked = msgspec.convert(request, stype.request)
        except msgspec.ValidationError as exc:
            raise BindingError("BAD_VALUE", f"not a {stype.name} request: {exc}") from None
        with self._lock:
            provider = self._providers.get(service)
        if provider is None:
            raise BindingError("NO_SERVICE", f"no server for service '{service}'")
        if provider.stype is not stype:
            raise BindingError(
                "TYPE_CLASH",
                f"service '{service}' has type {provider.stype.name}, not {stype.name}")
        reply = WaitingReply(stype)
        try:
            provider.handler(msgspec.to_builtins(checked), reply)
        except Exception as exc:  # a provider that raises has failed this request
            reply.fail(f"{type(exc).__name__}: {exc}")
        if not reply.wait(timeout):
            reply.fail("timed out")  # a late answer is dropped
            raise BindingError(
                "TIMEOUT", f"service '{service}' did not answer within {timeout:g} s")
        if reply.failure is not None:
            raise BindingError("SERVICE_FAILED", f"service '{service}' failed: {reply.failure}")
        assert reply.response is not None
        return reply.response

    def serve(self, service: str, srv_type: str, handler: ServiceHandler) -> _Provider:
        stype = self.service_type(srv_type)
        check_service_name(service)
        with self._lock:
            if service in self._providers:
                raise BindingError("CHANNEL_IN_USE", f"service '{service}' already has a server")
            provider = self._providers[service] = _Provider(service, stype, handler, self)
        return provider

    def remove(self, provider: _Provider) -> None:
        with self._lock:
            if self._providers.get(provider.name) is provider:
                del self._providers[provider.name]

    def listing(self) -> list[tuple[str, str]]:
        with self._lock:
            return sorted((p.name, p.stype.name) for p in self._providers.values())

    def clear(self) -> None:
        with self._lock:
            self._providers.clear()
