"""No option is ignored: every combination that cannot take effect is refused at the call.

One case per rule (docs/api.md has the table): the call raises ``ValueError`` naming the
option, and nothing happened: no channel was bound on the server, no session was opened.
The option objects' own checks run where they are built; the call's checks before any packet.
"""

from __future__ import annotations

import inspect
import ssl
import threading
from collections.abc import Callable
from typing import Any

import pytest

from rlbridge import Backoff, Bridge, Policy, Psk, QoS, SafeValue, Tls, Tuning
from rlbridge.server import ServerThread

F64 = "std_msgs/msg/Float64"
KEY = "ab" * 32


def _keyword_only(function: Callable[..., Any]) -> list[str]:
    return [name for name, p in inspect.signature(function).parameters.items()
            if p.kind is inspect.Parameter.KEYWORD_ONLY]


def test_calls_take_few_keyword_options() -> None:
    """The issue's budget: connect <= 8 keyword-only options, publish and subscribe <= 7."""
    assert len(_keyword_only(Bridge.connect)) <= 8
    assert len(_keyword_only(Bridge.publish)) <= 7
    assert len(_keyword_only(Bridge.subscribe)) <= 7
    gone = {"psk", "psk_file", "tls", "ca", "fingerprint", "client_cert", "control", "idle",
            "bundles", "switch_interval", "redundancy", "latest", "max_age_ms", "reliability",
            "depth", "durability", "on_lost", "flow", "max_rate_hz", "adapt_rate"}
    for call in (Bridge.connect, Bridge.publish, Bridge.subscribe):
        assert not gone & set(inspect.signature(call).parameters), call.__name__


#: Rules of the option objects alone: (what is built, the words the error must contain).
OBJECT_RULES: dict[str, tuple[Callable[[], object], str]] = {
    "max_age_ms negative": (lambda: Policy(max_age_ms=-1), r"max_age_ms=-1\): must be >= 0"),
    "redundancy out of range": (lambda: Policy(redundancy=17), r"redundancy=17\): must be 0..16"),
    "max_rate_hz not positive": (lambda: Policy(max_rate_hz=0.0), r"max_rate_hz=0.0\): must be"),
    "adapt_rate without max_rate_hz": (lambda: Policy(adapt_rate=True),
                                       r"adapt_rate=True\) needs max_rate_hz"),
    "flow with latest": (lambda: Policy(flow=True, latest=True), r"flow=True, latest=True"),
    "on_lost unknown": (lambda: Policy(on_lost="zero"),  # type: ignore[arg-type]
                        r"on_lost='zero'\): must be 'hold', 'raise' or SafeValue"),
    "setpoint without an age limit": (lambda: Policy.setpoint(max_age_ms=0),
                                      r"setpoint\(max_age_ms=0\): a set-point needs"),
    "QoS reliability unknown": (lambda: QoS(reliability="sometimes"),  # type: ignore[arg-type]
                                r"reliability='sometimes'\): must be"),
    "QoS durability unknown": (lambda: QoS(durability="forever"),  # type: ignore[arg-type]
                               r"durability='forever'\): must be"),
    "Psk with neither key nor file": (Psk, r"exactly one of key=.*got neither"),
    "Psk with both key and file": (lambda: Psk(key=KEY, file="keys"),
                                   r"exactly one of key=.*got both"),
    "Tls context with other fields": (
        lambda: Tls(context=ssl.create_default_context(), ca="ca.crt"),
        r"Tls\(context=...\) is the whole TLS set-up"),
    "Tls ca with fingerprint": (lambda: Tls(ca="ca.crt", fingerprint="ab" * 32),
                                r"pinned fingerprint replaces the CA check"),
    "Tls client_cert not a pair": (lambda: Tls(client_cert=("a",)),  # type: ignore[arg-type]
                                   r"client_cert=...\) is a \(certificate file, key file\)"),
    "Tuning control unknown": (lambda: Tuning(control="sctp"),  # type: ignore[arg-type]
                               r"control='sctp'\): must be 'tcp' or 'udp'"),
    "Tuning switch_interval not positive": (lambda: Tuning(switch_interval=0.0),
                                            r"switch_interval=0.0\): must be a positive"),
}


@pytest.mark.parametrize("rule", sorted(OBJECT_RULES))
def test_an_option_object_refuses_what_cannot_take_effect(rule: str) -> None:
    build, words = OBJECT_RULES[rule]
    with pytest.raises(ValueError, match=words):
        build()


def test_the_presets_are_what_the_docs_teach() -> None:
    """The mechanism behind the presets: which fields they set, and that they are valid."""
    point = Policy.setpoint(max_age_ms=50, on_lost=SafeValue(0.0))
    assert (point.latest, point.max_age_ms, point.on_lost) == (True, 50, SafeValue(0.0))
    assert Policy.every_value() == Policy(flow=True)
    with pytest.raises(AttributeError):
        point.latest = False  # type: ignore[misc]  # frozen: one object, shared safely


#: Rules of subscribe and publish: (call, keyword arguments, the words the error must contain).
CALL_RULES: dict[str, tuple[str, dict[str, Any], str]] = {
    "subscribe: unknown transport": ("subscribe", {"transport": "sctp"},
                                     r"subscribe\(\): transport='sctp' must be"),
    "subscribe: buffer_size 0": ("subscribe", {"buffer_size": 0}, r"buffer_size >= 1"),
    "subscribe: QoS depth 0": ("subscribe", {"qos": QoS(depth=0)}, r"depth must be >= 1"),
    "subscribe: initial on a blocking channel": (
        "subscribe", {"blocking": True, "initial": 0.0}, r"subscribe\(\): initial= is what"),
    "subscribe: redundancy on TCP": ("subscribe", {"transport": "tcp",
                                                   "policy": Policy(redundancy=1)},
                                     r"redundancy=1\) repeats values in UDP datagrams"),
    "subscribe: flow on UDP": ("subscribe", {"policy": Policy(flow=True)},
                               r"flow=True\) needs transport='tcp'"),
    "subscribe: max_rate_hz": ("subscribe", {"policy": Policy(max_rate_hz=100.0)},
                               r"max_rate_hz=..., adapt_rate=...\) limits what a publisher"),
    "subscribe: not a Policy": ("subscribe", {"policy": {"latest": True}},
                                r"must be a Policy"),
    "subscribe: not a QoS": ("subscribe", {"qos": "reliable"}, r"must be a QoS"),
    "publish: unknown transport": ("publish", {"transport": "quic"},
                                   r"publish\(\): transport='quic' must be"),
    "publish: buffer_size 0": ("publish", {"buffer_size": 0}, r"buffer_size >= 1"),
    "publish: QoS depth 0": ("publish", {"qos": QoS(depth=0)}, r"depth must be >= 1"),
    "publish: redundancy on TCP": ("publish", {"transport": "tcp",
                                               "policy": Policy(redundancy=2)},
                                   r"redundancy=2\) repeats values in UDP datagrams"),
    "publish: flow on UDP": ("publish", {"policy": Policy.every_value()},
                             r"flow=True\) needs transport='tcp'"),
    "publish: on_lost": ("publish", {"policy": Policy(on_lost=SafeValue(0.0))},
                         r"publish\(\): Policy\(on_lost=SafeValue"),
    "publish: durability match": ("publish", {"qos": QoS(durability="match")},
                                  r"QoS\(durability='match'\) copies the QoS"),
}


@pytest.mark.parametrize("rule", sorted(CALL_RULES))
def test_a_channel_call_refuses_what_cannot_take_effect(
        rule: str, bridge: Callable[..., Bridge]) -> None:
    verb, options, words = CALL_RULES[rule]
    b = bridge()
    with pytest.raises(ValueError, match=words):
        getattr(b, verb)("/rules", F64, **options)
    assert b.server_stats()["session"]["channels"] == {}  # refused before any binding
    # The same call without the offending option binds (the rule is about the combination).
    fine = getattr(b, verb)("/rules", F64)
    assert fine.channel_id in {int(k) for k in b.server_stats()["session"]["channels"]}


#: Rules of Bridge.connect: (keyword arguments, the words the error must contain).
CONNECT_RULES: dict[str, tuple[dict[str, Any], str]] = {
    "security not Psk or Tls": ({"security": KEY}, r"security='ab.*must be Psk"),
    "reconnect not bool or Backoff": ({"reconnect": 3}, r"reconnect=3 must be True, False"),
    "tuning not a Tuning": ({"tuning": {"control": "udp"}}, r"must be a Tuning"),
    "timeout not positive": ({"timeout": 0}, r"timeout=0 must be a positive"),
    "send_rate_hz not positive": ({"send_rate_hz": 0.0}, r"send_rate_hz=0.0 must be positive"),
    "TLS without a TCP connection": ({"security": Tls(), "tuning": Tuning(control="udp")},
                                     r"security=Tls\(...\) protects the TCP connection"),
    "nodelay without a TCP connection": ({"nodelay": True, "tuning": Tuning(control="udp")},
                                         r"nodelay=True turns off Nagle"),
}


@pytest.mark.parametrize("rule", sorted(CONNECT_RULES))
def test_connect_refuses_what_cannot_take_effect(rule: str, server: ServerThread) -> None:
    options, words = CONNECT_RULES[rule]
    before = threading.active_count()
    with pytest.raises(ValueError, match=words):
        Bridge.connect("127.0.0.1", server.port, **options)
    assert threading.active_count() == before  # refused before any socket or thread
    assert server.server.registry is not None
    assert server.server.registry.ctx.counters.get("sessions_opened", 0) == 0


def test_backoff_and_good_objects_are_accepted(server: ServerThread) -> None:
    """The other side of the rules: the grouped options a program normally passes work."""
    with Bridge.connect("127.0.0.1", server.port, reconnect=Backoff(initial=0.01),
                        tuning=Tuning(idle="spin")) as b:
        ch = b.subscribe("/ok", F64, qos=QoS(reliability="reliable", depth=5),
                         policy=Policy.setpoint(max_age_ms=100, on_lost="raise"))
        out = b.publish("/ok", F64, transport="tcp", policy=Policy.every_value())
        assert out.flow
        assert ch.latest
    assert server.server.registry is not None  # the counter the refusals above leave at 0
    assert server.server.registry.ctx.counters.get("sessions_opened", 0) == 1
