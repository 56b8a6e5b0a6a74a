"""The API reference (docs/api.md) from signatures and docstrings, with :mod:`inspect`.

Part of ``scripts/gen_docs.py``, which imports it; :data:`API` is the list of what is public.
Objects render in that order and members in source order, so the output is stable. Docstrings
are reST-ish; the few constructs they use (roles, underlined titles) become Markdown.
"""

from __future__ import annotations

import ast
import dataclasses
import enum
import importlib
import inspect
import re
import types
from collections.abc import Callable, Iterator
from typing import Any


def anchor(title: str) -> str:
    """GitHub's heading anchor for a heading of words, dots, dashes and spaces."""
    keep = "".join(c for c in title.lower() if c.isalnum() or c in " -_")
    return keep.replace(" ", "-")

# (heading, module, names, why): the public API, in reading order.
API: list[tuple[str, str, list[str], str]] = [
    ("Bridge: the session with a server", "rlbridge.client.bridge", ["Bridge"],
     "Start here: `Bridge.connect` opens a session, `subscribe`/`publish` return channels."),
    ("", "rlbridge.client.options", ["Policy", "Psk", "Tls", "Tuning", "Transport"],
     "The grouped options of `connect`, `subscribe` and `publish` (with `QoS`)."),
    ("I/O idle strategies", "rlbridge.csp.idle",
     ["IdleStrategy", "Park", "SpinThenPark", "BusySpin", "idle_strategy"],
     "`Bridge.connect(idle=...)`: how the SDK's send and receive threads wait for work "
     "([concepts.md](concepts.md#io-threads-how-they-wait-idle-strategies))."),
    ("Bridge channels", "rlbridge.client.channels.incoming",
     ["IncomingChannel", "OutgoingChannel", "AgedValue", "SecondWriterError"],
     "What `Bridge.subscribe` and `Bridge.publish` return."),
    ("Write-time type checks", "rlbridge.errors", ["WrongValueType"],
     "`OutgoingChannel.write` of a value that cannot be the bound field's type raises this "
     "`TypeError` ([concepts.md](concepts.md#values-are-checked-where-they-are-written))."),
    ("Channel health", "rlbridge.client.channels.health", ["ChannelHealth"],
     "`channel.health()`: link health per channel, readable from control code "
     "([policies.md](policies.md))."),
    ("Reconnect", "rlbridge.client.session.reconnect", ["Backoff", "ClientState"],
     "`Bridge.connect(reconnect=...)`: how the SDK rides out a server restart or an outage "
     "([reliability.md](reliability.md))."),
    ("Link events and fail-safes", "rlbridge.client.session.link_events", ["LinkEvent"],
     "`Bridge.link_events()` and `Bridge.subscribe(on_lost=...)`."),
    ("", "rlbridge.client.channels.failsafe", ["SafeValue"], ""),
    ("", "rlbridge.errors", ["LinkLost"], ""),
    ("Authentication", "rlbridge.client.session.auth", ["resolve_key"],
     "`Bridge.connect(psk=...)` for a server started with a pre-shared key "
     "([security.md](security.md))."),
    ("HRT loop in its own process", "rlbridge.hrt.shm", ["ShmLink", "HrtProcess", "forwarder",
                                                        "ShmLinkError"],
     "The design that keeps a 1 kHz loop's jitter at the reference loop's "
     "([gil.md](gil.md), [jitter.md](jitter.md))."),
    ("GIL switch interval", "rlbridge.hrt.gil",
     ["shorter_switch_interval", "realtime_switch_interval", "HRT_SWITCH_INTERVAL"], ""),
    ("Link state and connection errors", "rlbridge.wire.link", ["LinkState"],
     "What control code branches on when the network misbehaves."),
    ("", "rlbridge.client.session.connection", ["ConnectionFailed", "ConnectionClosed"], ""),
    ("Errors from the server", "rlbridge.errors",
     ["RlbridgeError", "LocalProtocolError", "RemoteProtocolError", "RemoteError",
      "BindingRefused", "UnknownTypeError", "TypeClashError", "NoSuchFieldError",
      "BadValueError", "LimitExceeded", "ServerShuttingDown"],
     "Who is at fault: this program (local), the peer's bytes (remote protocol), or the "
     "server's answer (remote error, one class per wire error code)."),
    ("CSP channels", "rlbridge.csp.channel", ["Channel", "ChannelStatistics", "Doorbell"],
     "Local channels between processes of the control program."),
    ("Channel errors and warnings", "rlbridge.errors",
     ["ChannelError", "ChannelClosed", "WouldBlock", "NoValueYet", "ChannelMisuseError",
      "RealTimeWarning"], ""),
    ("Ring buffers", "rlbridge.csp.ring", ["SpscRing", "MpscRing", "EMPTY"],
     "The lock-free storage under every buffered channel; use them directly only for your "
     "own hand-offs between exactly the threads they allow."),
    ("Processes", "rlbridge.csp.process",
     ["Process", "Code", "Sequential", "Parallel", "PriParallel", "Recursion"],
     "The CSP constructs of the thesis (figure 2.4) on threads."),
    ("Periodic timer", "rlbridge.csp.timer", ["PeriodicTimer", "Timed", "LatenessStats"], ""),
    ("Coupling patterns", "rlbridge.hrt.patterns",
     ["BaseCoupling", "Coupling", "ControlLoop", "reference", "receive_nonblocking",
      "receive_blocking", "receive_naive", "send_buffered", "send_sampled", "send_loop",
      "send_naive", "realtime_switch_interval"],
     "Ready-made compositions of an HRT loop with the bridge (thesis chapter 5); "
     "[concepts.md](concepts.md#coupling-patterns-which-one-for-which-need) says which to pick."),
    ("The loop in its own process (the patterns' default layout)", "rlbridge.hrt.isolated",
     ["IsolatedCoupling", "Layout", "DEFAULT_LAYOUT", "LoopSpec", "LoopReport",
      "check_picklable"],
     "What `layout=\"process\"` builds; [gil.md](gil.md) says why it is the default."),
    ("", "rlbridge.hrt.patterns_process",
     ["receive_nonblocking", "receive_blocking", "send_buffered", "send_sampled", "send_loop"],
     "The SRT side of each pattern in the process layout (called by `rlbridge.hrt.patterns`)."),
    ("Real-time set-up of a loop process", "rlbridge.hrt.rtenv",
     ["prepare_hrt_process", "thread_scheduling"], ""),
    ("Middleware adapters", "rlbridge.adapters.base",
     ["MiddlewareAdapter", "Publisher", "Subscription", "QoS", "ValueSpec", "BindingError",
      "ValuesCallback"],
     "Implement `MiddlewareAdapter` to put the bridge in front of another middleware; "
     "`tests/adapters/contract.py` is the conformance suite it must pass."),
    ("", "rlbridge.adapters", ["load_adapter", "AdapterUnavailable", "InProcessBus"], ""),
    ("Embedding the server", "rlbridge.server.config", ["ServerConfig"],
     "`rlbridge serve` builds a `ServerConfig` and calls `Server(config).run()`; so can your "
     "program. `ServerThread` runs it in a background thread (tests, examples, one-process "
     "set-ups):\n\n```python\nfrom rlbridge import Bridge\n"
     "from rlbridge.server import ServerConfig, ServerThread\n\n"
     "with ServerThread(ServerConfig(port=0, nodelay=True)) as server:  # port 0: any free port\n"
     "    with Bridge.connect(\"127.0.0.1\", server.port) as bridge:\n"
     "        print(bridge.link_state)\n```"),
    ("", "rlbridge.server.app",
     ["Server", "ServerThread", "BoundAddress", "ServerError", "new_event_loop"], ""),
]

# Classes whose methods are documented elsewhere (an adapter: the Protocol's methods).
CLASS_ONLY = {"rlbridge.adapters.InProcessBus"}

MISSING: list[str] = []  # "module.name" of public objects without a docstring


_ROLE = re.compile(r":(?:meth|class|func|data|attr|mod|exc):`(~?)([^`]+)`")
_UNDERLINE = re.compile(r"^(\S[^\n]*)\n[-=~]{3,}$", re.MULTILINE)


def _markdown(doc: str) -> str:
    """The reST bits our docstrings use, as Markdown: roles as code, underlined titles bold."""
    doc = _ROLE.sub(lambda m: f"`{m[2].rsplit('.', 1)[-1] if m[1] else m[2]}`", doc)
    return _UNDERLINE.sub(lambda m: f"**{m[1]}**", doc)


def _doc(obj: Any, qualname: str) -> str:
    doc = inspect.getdoc(obj)
    if doc and inspect.isclass(obj) and dataclasses.is_dataclass(obj) \
            and doc.startswith(f"{obj.__name__}("):
        doc = None  # the signature dataclasses writes when the author wrote nothing
    if not doc:
        MISSING.append(qualname)
        return "*(no docstring)*"
    return _markdown(doc)


def _default(value: Any) -> str:
    if inspect.isroutine(value):  # a function's repr carries its address
        return str(value.__qualname__)
    if isinstance(value, enum.Enum):
        return f"{type(value).__name__}.{value.name}"
    return repr(value)


def _signature(obj: Callable[..., Any], *, drop_self: bool = False) -> str:
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):
        return "(...)"
    params = list(sig.parameters.values())
    if drop_self and params and params[0].name in ("self", "cls"):
        params = params[1:]
    parts: list[str] = []
    star_done = False
    for p in params:
        if p.kind is p.KEYWORD_ONLY and not star_done:
            parts.append("*")
            star_done = True
        if p.kind is p.VAR_POSITIONAL:
            star_done = True
        prefix = "*" if p.kind is p.VAR_POSITIONAL else "**" if p.kind is p.VAR_KEYWORD else ""
        text = prefix + p.name
        if p.annotation is not p.empty:
            text += f": {_annotation(p.annotation)}"
        if p.default is not p.empty:
            text += f" = {_default(p.default)}" if p.annotation is not p.empty else \
                f"={_default(p.default)}"
        parts.append(text)
        if p.kind is p.POSITIONAL_ONLY and (p is params[-1] or
                                            params[params.index(p) + 1].kind is not p.kind):
            parts.append("/")
    ret = ""
    if sig.return_annotation is not sig.empty:
        ret = f" -> {_annotation(sig.return_annotation)}"
    return f"({', '.join(parts)}){ret}"


def _annotation(ann: Any) -> str:
    if isinstance(ann, str):
        return ann
    if isinstance(ann, type) and not isinstance(ann, types.GenericAlias):  # 3.10: an alias is
        return ann.__name__                                                   # a type too
    # pathlib._local: where Python 3.13 defines Path; the docs read the same on 3.10 to 3.13.
    return repr(ann).replace("typing.", "").replace("pathlib._local.", "pathlib.")


def _attribute_docs(module: Any) -> dict[str, str]:
    """Docstrings of module-level names: a string after the assignment, or ``#:`` comments."""
    source = inspect.getsource(module)
    lines = source.splitlines()
    docs: dict[str, str] = {}
    body = ast.parse(source).body
    for i, node in enumerate(body):
        if isinstance(node, ast.Assign) and len(node.targets) == 1:
            target = node.targets[0]
        elif isinstance(node, ast.AnnAssign):
            target = node.target
        else:
            continue
        if not isinstance(target, ast.Name):
            continue
        nxt = body[i + 1] if i + 1 < len(body) else None
        if (isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)):
            docs[target.id] = inspect.cleandoc(nxt.value.value)
            continue
        comment: list[str] = []
        j = node.lineno - 2
        while j >= 0 and lines[j].lstrip().startswith("#:"):
            comment.insert(0, lines[j].lstrip()[2:].strip())
            j -= 1
        if comment:
            docs[target.id] = " ".join(comment)
    return docs


def _members(cls: type) -> Iterator[tuple[str, Any]]:
    """Public methods and properties defined in ``cls`` itself, in source order."""
    for name, raw in vars(cls).items():
        if name.startswith("_"):
            continue
        if isinstance(raw, (staticmethod, classmethod, property)) or inspect.isfunction(raw):
            yield name, raw


def _render_member(cls: type, name: str, raw: Any, qual: str) -> list[str]:
    if isinstance(raw, property):
        ret = ""
        if raw.fget is not None:
            ann = inspect.signature(raw.fget).return_annotation
            ret = "" if ann is inspect.Signature.empty else f": {_annotation(ann)}"
        head = f"#### `{cls.__name__}.{name}{ret}` (property)"
        doc = _doc(raw, f"{qual}.{name}")
    else:
        func = raw.__func__ if isinstance(raw, (staticmethod, classmethod)) else raw
        kind = " (classmethod)" if isinstance(raw, classmethod) else ""
        sig = _signature(func, drop_self=not isinstance(raw, staticmethod))
        head = f"#### `{cls.__name__}.{name}{sig}`{kind}"
        doc = _doc(getattr(cls, name), f"{qual}.{name}")
    return [head, "", doc, ""]


def _bases(cls: type) -> str:
    names = [b.__name__ for b in cls.__bases__
             if b is not object and b.__name__ not in ("Generic", "ABC")]
    return f"({', '.join(names)})" if names else ""


def _render_class(cls: type, qual: str) -> list[str]:
    out = [f"### `{cls.__name__}`", ""]
    is_protocol = getattr(cls, "_is_protocol", False)
    if issubclass(cls, enum.Enum):
        members = ", ".join(f"`{m.name}` = `{m.value!r}`" for m in cls)
        out += [f"`class {cls.__name__}{_bases(cls)}`: {members}", ""]
    elif is_protocol or issubclass(cls, BaseException) or hasattr(cls, "model_fields"):
        out += [f"`class {cls.__name__}{_bases(cls)}`", ""]
    else:
        sig = _signature(cls).removesuffix(" -> None")
        out += ["```python", f"class {cls.__name__}{sig}", "```",
                f"Bases: `{_bases(cls)[1:-1]}`" if _bases(cls) else "", ""]
    out += [_doc(cls, qual), ""]
    if is_protocol:
        for attr, ann in inspect.get_annotations(cls).items():
            out += [f"- attribute `{attr}: {_annotation(ann)}`", ""]
    fields = getattr(cls, "model_fields", None)
    if fields:
        out += ["| field | type | default | range | meaning |", "|---|---|---|---|---|"]
        for fname, info in fields.items():
            ann = _annotation(info.annotation).replace("|", "\\|")
            out.append(f"| `{fname}` | `{ann}` | `{_default(info.default)}` | "
                       f"{_bounds(info.metadata)} | {info.description or ''} |")
        out.append("")
        return out
    if issubclass(cls, BaseException) or dataclasses.is_dataclass(cls) or qual in CLASS_ONLY:
        return out
    for name, raw in _members(cls):
        if _inherits_doc(cls, name, raw):
            continue  # an override the base class documents already (``execute``)
        out += _render_member(cls, name, raw, qual)
    return out


def _bounds(metadata: list[Any]) -> str:
    """``ge``/``le`` style constraints of a pydantic field as ``0 ≤ x ≤ 65535``."""
    low = high = ""
    for item in metadata:
        for attr, sign in (("ge", " ≤"), ("gt", " <")):
            if getattr(item, attr, None) is not None:
                low = f"{getattr(item, attr)}{sign} "
        for attr, sign in (("le", "≤ "), ("lt", "< ")):
            if getattr(item, attr, None) is not None:
                high = f" {sign}{getattr(item, attr)}"
    return f"{low}x{high}" if low or high else ""


def _inherits_doc(cls: type, name: str, raw: Any) -> bool:
    func = raw.__func__ if isinstance(raw, (staticmethod, classmethod)) else raw
    own = func.fget.__doc__ if isinstance(func, property) and func.fget else func.__doc__
    return not own and any(name in vars(base) for base in cls.__mro__[1:])


def render_api(header: str) -> str:
    """docs/api.md; ``header`` is its first line. Fills :data:`MISSING` as it goes."""
    out = [header,
           "# SDK and server API reference\n",
           "The public API of the client SDK (`rlbridge.csp`), the adapter Protocol and the "
           "server for embedding, in reading order. Signatures are as written in the source "
           "(`from __future__ import annotations`). Concepts: [concepts.md](concepts.md); "
           "threads and real-time rules: [design.md](design.md).\n"]
    toc: list[str] = []
    body: list[str] = []
    for heading, modname, names, why in API:
        module = importlib.import_module(modname)
        if heading:
            toc.append(f"- [{heading}](#{anchor(heading)})")
            body += [f"## {heading}", ""]
            if why:
                body += [why, ""]
        body += [f"Module `{modname}`.", ""]
        if module.__doc__:
            body += [_markdown(inspect.cleandoc(module.__doc__)), ""]
        attr_docs = _attribute_docs(module)
        for name in names:
            obj = getattr(module, name)
            qual = f"{modname}.{name}"
            # On Python 3.10 an alias such as ``Callable[[int], None]`` passes isclass() too.
            if inspect.isclass(obj) and not isinstance(obj, types.GenericAlias):
                body += _render_class(obj, qual)
            elif inspect.isfunction(obj):
                body += [f"### `{name}{_signature(obj)}`", "", _doc(obj, qual), ""]
            else:
                doc = _markdown(attr_docs.get(name, ""))
                if not doc:
                    MISSING.append(qual)
                    doc = "*(no docstring)*"
                body += [f"### `{name}`", "", f"`{name} = {_value(obj)}`", "", doc, ""]
    text = "\n".join([*out, *toc, "", *body]).rstrip() + "\n"
    while "\n\n\n" in text:
        text = text.replace("\n\n\n", "\n\n")
    return text


def _value(obj: Any) -> str:
    if isinstance(obj, enum.Enum):
        return f"{type(obj).__name__}.{obj.name}"
    return _annotation(obj) if not isinstance(obj, (int, float, str)) else repr(obj)
