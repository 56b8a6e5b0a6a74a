"""ROS 2 services through the adapter's node: calls that block their caller, and providers
whose answers come later, from another thread.

Calling. :meth:`Ros2Services.call` runs on a worker thread of the server (never the event loop,
never the executor thread): it waits for the service to be discovered, sends the request with
``call_async`` and waits for the executor thread to complete the future. One rclpy client per
(service, type) is kept, so only the first call pays for discovery.

Providing. rclpy wants a service callback to *return* the response, but the answer of a
service provided by a bridge client comes over the network, later. So the callback returns at
once and the response is sent afterwards with ``Service.send_response(response, header)``:
rclpy's executor calls ``send_response`` on the service right after the callback, with the
request's header, and :class:`_DeferredService` replaces that call per service object to keep
the header until the client answers. (An ``async`` callback awaiting a future would do the
same, but rclpy's executor resumes a pending coroutine on every turn of its loop: it would spin
a core while a request waits.) ROS 2 services have no error reply: a provider that fails sends
nothing, and the caller's own timeout tells it. Closing the adapter ends every call still
waiting, with the closed adapter's error, instead of leaving it to its timeout.
"""

from __future__ import annotations

import importlib
import logging
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from rlbridge.adapters.base import BindingError, ServiceHandler
from rlbridge.adapters.inproc_services import normalize_service_type
from rlbridge.adapters.ros2_codecs import whole_encoder
from rlbridge.adapters.ros2_rclpy import InvalidHandle, Node, RCLError, RclpyService
from rlbridge.adapters.ros2_types import MessageCatalog, pip_package

log = logging.getLogger("rlbridge.adapters.ros2")

_PACKAGE_RE = re.compile(r"[a-z][a-z0-9_]*\Z")
_TYPE_RE = re.compile(r"[A-Z][A-Za-z0-9]*\Z")


class ServiceOwner(Protocol):
    """What services and actions use of the adapter that owns the node.

    A Protocol, so this module needs no import of :mod:`.ros2` (which imports this one).
    """

    catalog: MessageCatalog
    lock: threading.RLock
    node: Node

    def check_open(self) -> None: ...

    def full_topic_name(self, topic: str) -> str: ...

    def release_service(self, provider: Any) -> None: ...


@dataclass(frozen=True, slots=True)
class Half:
    """One message of an interface (a request, a response, a goal, ...): dict <-> message."""

    encode: Callable[[Any], Any]
    decode: Callable[[Any], dict[str, Any]]


def half(catalog: MessageCatalog, name: str, cls: type[Any]) -> Half:
    codec = catalog.class_codec(name, cls)
    return Half(whole_encoder(codec), codec.to_plain)


def interface_class(srv_type: str, kind: str,
                    importer: Callable[[str], Any] = importlib.import_module) -> tuple[str, Any]:
    """``'std_srvs/srv/SetBool'`` (kind ``srv``; ``action`` alike) -> (name, class)."""
    if kind == "srv":
        name = normalize_service_type(srv_type)
    else:
        parts = srv_type.strip().split("/")
        if len(parts) == 2:
            parts = [parts[0], kind, parts[1]]
        name = "/".join(parts)
    package, middle, type_name = ([*name.split("/"), "", ""])[:3]
    if middle != kind or not (_PACKAGE_RE.match(package) and _TYPE_RE.match(type_name)):
        raise BindingError(
            "UNKNOWN_TYPE", f"'{srv_type}' is not a ROS 2 {kind} type name, e.g. "
            + ("'std_srvs/srv/SetBool'" if kind == "srv" else "'test_msgs/action/Fibonacci'"))
    try:
        module = importer(f"{package}.{kind}")
    except ModuleNotFoundError:
        raise BindingError(
            "UNKNOWN_TYPE", f"'{package}' is not an installed ROS 2 package with {kind} types "
            f"(install it with: pip install {pip_package(package)})") from None
    cls = getattr(module, type_name, None)
    if cls is None or not hasattr(cls, "Request" if kind == "srv" else "Goal"):
        known = sorted(n for n in vars(module) if _TYPE_RE.match(n) and not n.startswith("_"))
        raise BindingError(
            "UNKNOWN_TYPE", f"unknown {'service' if kind == 'srv' else kind} type "
            f"'{srv_type}'; {package} has: {', '.join(known)}")
    return name, cls


@dataclass(frozen=True, slots=True)
class ServiceCodec:
    name: str
    cls: Any
    request: Half
    response: Half


def service_codec(catalog: MessageCatalog, srv_type: str) -> ServiceCodec:
    name, cls = interface_class(srv_type, "srv")
    return ServiceCodec(name, cls, half(catalog, f"{name}_Request", cls.Request),
                        half(catalog, f"{name}_Response", cls.Response))


class _Pending:
    """One request of a provided service: its header (from rclpy) and its answer (from us)."""

    __slots__ = ("answered", "header", "message")

    def __init__(self) -> None:
        self.header: Any = None
        self.message: Any = None
        self.answered = False


class _Reply:
    """The :class:`~rlbridge.adapters.base.ServiceReply` of one request to a ROS 2 service."""

    def __init__(self, service: _DeferredService, template: Any) -> None:
        self._service = service
        self._template = template

    def send(self, response: dict[str, Any]) -> None:
        message = self._service.codec.response.encode(response)  # BAD_VALUE before anything
        self._service.answer(self._template, message)

    def fail(self, reason: str) -> None:
        self._service.failed += 1
        log.warning("ros2 service %s: request not answered: %s", self._service.name, reason)
        self._service.answer(self._template, None)


class _DeferredService:
    """A provided service whose responses are sent when the client answers; see module doc."""

    def __init__(self, adapter: ServiceOwner, name: str, codec: ServiceCodec,
                 handler: ServiceHandler) -> None:
        self.name = name
        self.codec = codec
        self.failed = 0
        self._adapter = adapter
        self._handler = handler
        self._lock = threading.Lock()
        self._pending: dict[int, _Pending] = {}  # by id() of the response template
        self._closed = False
        self.ros: RclpyService[Any, Any] | None = None

    def on_request(self, request: Any, template: Any) -> Any:
        """Executor thread: hand the request on; the template comes back to send_response."""
        with self._lock:
            self._pending[id(template)] = _Pending()
        try:
            self._handler(self.codec.request.decode(request), _Reply(self, template))
        except Exception:
            log.exception("ros2 service %s: handing a request on failed", self.name)
            self.answer(template, None)
        return template

    def send_response(self, template: Any, header: Any) -> None:
        """Executor thread, right after ``on_request``: keep the header until the answer."""
        with self._lock:
            pending = self._pending.get(id(template))
            if pending is None:
                return
            pending.header = header
            ready = pending.answered
            if ready:
                del self._pending[id(template)]
        if ready:
            self._send(pending)

    def answer(self, template: Any, message: Any) -> None:
        """Any thread: the answer (``None``: none will come); sent once the header is known."""
        with self._lock:
            pending = self._pending.get(id(template))
            if pending is None or pending.answered:
                return
            pending.answered, pending.message = True, message
            ready = pending.header is not None
            if ready:
                del self._pending[id(template)]
        if ready:
            self._send(pending)

    def _send(self, pending: _Pending) -> None:
        ros = self.ros
        if pending.message is None or ros is None or self._closed:
            return
        try:
            RclpyService.send_response(ros, pending.message, pending.header)
        except Exception as exc:  # destroyed meanwhile, or rmw refused: the caller times out
            log.warning("ros2 service %s: sending a response failed: %s", self.name, exc)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._pending.clear()
        self._adapter.release_service(self)


class Ros2Services:
    """The adapter's service clients and providers (the adapter's lock guards the tables)."""

    def __init__(self, adapter: ServiceOwner) -> None:
        self._adapter = adapter
        self._clients: dict[tuple[str, str], Any] = {}
        self.providers: set[_DeferredService] = set()
        #: What each waiting call waits on; clear() (the adapter closing) sets them all.
        self._waiting: set[threading.Event] = set()

    def call(self, service: str, srv_type: str, request: dict[str, Any],
             timeout: float) -> dict[str, Any]:
        adapter = self._adapter
        codec = service_codec(adapter.catalog, srv_type)
        message = codec.request.encode(request)
        full = adapter.full_topic_name(service)
        done = threading.Event()
        with adapter.lock:
            adapter.check_open()
            client = self._clients.get((full, codec.name))
            if client is None:
                client = adapter.node.create_client(codec.cls, full)
                self._clients[(full, codec.name)] = client
            self._waiting.add(done)
        end = time.monotonic() + timeout
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                self._check_open()
                raise BindingError("NO_SERVICE", f"no server for service '{full}' "
                                   f"({codec.name}) within {timeout:g} s")
            future = client.call_async(message)
            future.add_done_callback(lambda _f: done.set())
            if not done.wait(max(0.0, end - time.monotonic())):
                client.remove_pending_request(future)
                raise BindingError("TIMEOUT",
                                   f"service '{full}' did not answer within {timeout:g} s")
            if not future.done():  # woken by close()
                self._check_open()
        except (InvalidHandle, RCLError):  # the client was destroyed with the closed adapter
            self._check_open()
            raise
        finally:
            with adapter.lock:
                self._waiting.discard(done)
        exc = future.exception()
        if exc is not None:
            raise BindingError("SERVICE_FAILED", f"service '{full}' failed: {exc}")
        return codec.response.decode(future.result())

    def serve(self, service: str, srv_type: str, handler: ServiceHandler) -> _DeferredService:
        adapter = self._adapter
        codec = service_codec(adapter.catalog, srv_type)
        full = adapter.full_topic_name(service)
        with adapter.lock:
            adapter.check_open()
            if any(p.name == full for p in self.providers):
                raise BindingError("CHANNEL_IN_USE",
                                   f"service '{full}' is already provided by this bridge")
            provider = _DeferredService(adapter, full, codec, handler)
            ros = adapter.node.create_service(codec.cls, full, provider.on_request)
            ros.send_response = provider.send_response  # type: ignore[method-assign,assignment]
            provider.ros = ros
            self.providers.add(provider)
        return provider

    def listing(self) -> list[tuple[str, str]]:
        node = self._adapter.node
        return sorted((name, t) for name, types in node.get_service_names_and_types()
                      for t in types)

    def _check_open(self) -> None:
        with self._adapter.lock:
            self._adapter.check_open()

    def clear(self) -> None:
        """The adapter is closing (under its lock): forget everything, wake waiting calls."""
        self._clients.clear()
        self.providers.clear()
        for done in self._waiting:
            done.set()

