"""No option is ignored: every combination that cannot take effect is refused at the call.

One case per rule (docs/api.md has the table): the call raises ``ValueError`` naming the
option, and nothing happened: no channel was bound on the server, no session was opened.
The option objects' own checks run where they are built; the call's checks before any packet.
"""

from __future__ import annotations

import inspect
import re
import ssl
import threading
from collections.abc import Callable
from typing import Any

import pytest

from rlbridge import Backoff, Bridge, Policy, Psk, QoS, SafeValue, Tls, Tuning
from rlbridge.csp.option_table import RULES, refuse
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


#: Rules of the option objects alone: rule (a row of RULES) -> (what is built, the option as
#: the message names it).
OBJECT_RULES: dict[str, tuple[Callable[[], object], str]] = {
    "policy_max_age": (lambda: Policy(max_age_ms=-1), "max_age_ms=-1"),
    "policy_redundancy": (lambda: Policy(redundancy=17), "redundancy=17"),
    "policy_rate": (lambda: Policy(max_rate_hz=0.0), "max_rate_hz=0.0"),
    "policy_adapt": (lambda: Policy(adapt_rate=True), "adapt_rate=True"),
    "policy_flow_latest": (lambda: Policy(flow=True, latest=True), "flow=True, latest=True"),
    "policy_on_lost": (lambda: Policy(on_lost="zero"),  # type: ignore[arg-type]
                       "on_lost='zero'"),
    "setpoint_age": (lambda: Policy.setpoint(max_age_ms=0), "max_age_ms=0"),
    "qos_reliability": (lambda: QoS(reliability="sometimes"),  # type: ignore[arg-type]
                        "reliability='sometimes'"),
    "qos_durability": (lambda: QoS(durability="forever"),  # type: ignore[arg-type]
                       "durability='forever'"),
    "psk_one": (Psk, "neither key= nor file= given:"),
    "tls_context": (lambda: Tls(context=ssl.create_default_context(), ca="ca.crt"),
                    "context= with ca=, fingerprint= or client_cert=:"),
    "tls_pin": (lambda: Tls(ca="ca.crt", fingerprint="ab" * 32), "ca= with fingerprint=:"),
    "tls_cert": (lambda: Tls(client_cert=("a",)),  # type: ignore[arg-type]
                 "client_cert=('a',)"),
    "tuning_control": (lambda: Tuning(control="sctp"),  # type: ignore[arg-type]
                       "control='sctp'"),
    "tuning_switch": (lambda: Tuning(switch_interval=0.0), "switch_interval=0.0"),
}


@pytest.mark.parametrize("rule", sorted(OBJECT_RULES))
def test_an_option_object_refuses_what_cannot_take_effect(rule: str) -> None:
    build, given = OBJECT_RULES[rule]
    expected = str(refuse(rule, given))  # this rule's row, naming this option
    with pytest.raises(ValueError, match=re.escape(expected)) as info:
        build()
    assert str(info.value) == expected


def test_psk_with_both_sources_is_refused_too() -> None:
    with pytest.raises(ValueError, match="key= and file= both given: give exactly one"):
        Psk(key=KEY, file="keys")


def test_the_presets_are_what_the_docs_teach() -> None:
    """The mechanism behind the presets: which fields they set, and that they are valid."""
    point = Policy.setpoint(max_age_ms=50, on_lost=SafeValue(0.0))
    assert (point.latest, point.max_age_ms, point.on_lost) == (True, 50, SafeValue(0.0))
    assert Policy.every_value() == Policy(flow=True)
    with pytest.raises(AttributeError):
        point.latest = False  # type: ignore[misc]  # frozen: one object, shared safely


#: Rules of subscribe and publish: case -> (rule, call, keyword arguments, the option as the
#: message names it).
CALL_RULES: dict[str, tuple[str, str, dict[str, Any], str]] = {
    "subscribe transport": ("transport", "subscribe", {"transport": "sctp"},
                            "transport='sctp'"),
    "subscribe buffer_size": ("buffer_size", "subscribe", {"buffer_size": 0}, "buffer_size=0"),
    "subscribe depth": ("depth", "subscribe", {"qos": QoS(depth=0)}, "QoS(depth=0)"),
    "subscribe initial": ("initial_blocking", "subscribe", {"blocking": True, "initial": 0.0},
                          "initial="),
    "subscribe redundancy tcp": ("redundancy_tcp", "subscribe",
                                 {"transport": "tcp", "policy": Policy(redundancy=1)},
                                 "Policy(redundancy=1)"),
    "subscribe flow udp": ("flow_udp", "subscribe", {"policy": Policy(flow=True)},
                           "Policy(flow=True)"),
    "subscribe rate": ("rate_subscribe", "subscribe", {"policy": Policy(max_rate_hz=100.0)},
                       "Policy(max_rate_hz=..., adapt_rate=...)"),
    "subscribe policy type": ("policy_type", "subscribe", {"policy": {"latest": True}},
                              "policy={'latest': True}"),
    "subscribe qos type": ("qos_type", "subscribe", {"qos": "reliable"}, "qos='reliable'"),
    "publish transport": ("transport", "publish", {"transport": "quic"}, "transport='quic'"),
    "publish buffer_size": ("buffer_size", "publish", {"buffer_size": 0}, "buffer_size=0"),
    "publish depth": ("depth", "publish", {"qos": QoS(depth=0)}, "QoS(depth=0)"),
    "publish redundancy tcp": ("redundancy_tcp", "publish",
                               {"transport": "tcp", "policy": Policy(redundancy=2)},
                               "Policy(redundancy=2)"),
    "publish flow udp": ("flow_udp", "publish", {"policy": Policy.every_value()},
                         "Policy(flow=True)"),
    "publish on_lost": ("on_lost_publish", "publish", {"policy": Policy(on_lost=SafeValue(0.0))},
                        "Policy(on_lost=SafeValue(value=0.0))"),
    "publish adapt tcp": ("adapt_tcp", "publish", {"transport": "tcp", "policy": Policy(
        max_rate_hz=100.0, adapt_rate=True)}, "Policy(adapt_rate=True)"),
    "publish match": ("match_publish", "publish", {"qos": QoS(durability="match")},
                      "QoS(durability='match')"),
}


@pytest.mark.parametrize("case", sorted(CALL_RULES))
def test_a_channel_call_refuses_what_cannot_take_effect(
        case: str, bridge: Callable[..., Bridge]) -> None:
    rule, verb, options, given = CALL_RULES[case]
    b = bridge()
    expected = str(refuse(rule, given, f"{verb}()"))
    with pytest.raises(ValueError, match=re.escape(expected)) as info:
        getattr(b, verb)("/rules", F64, **options)
    assert str(info.value) == expected
    assert b.server_stats()["session"]["channels"] == {}  # refused before any binding
    # The same call without the offending option binds (the rule is about the combination).
    fine = getattr(b, verb)("/rules", F64)
    assert fine.channel_id in {int(k) for k in b.server_stats()["session"]["channels"]}


#: Rules of Bridge.connect: rule -> (keyword arguments, the option as the message names it).
CONNECT_RULES: dict[str, tuple[dict[str, Any], str]] = {
    "security_type": ({"security": KEY}, f"security={KEY!r}"),
    "reconnect_type": ({"reconnect": 3}, "reconnect=3"),
    "tuning_type": ({"tuning": {"control": "udp"}}, "tuning={'control': 'udp'}"),
    "timeout": ({"timeout": 0}, "timeout=0"),
    "send_rate": ({"send_rate_hz": 0.0}, "send_rate_hz=0.0"),
    "tls_udp": ({"security": Tls(), "tuning": Tuning(control="udp")}, "security=Tls(...)"),
    "nodelay_udp": ({"nodelay": True, "tuning": Tuning(control="udp")}, "nodelay=True"),
}


@pytest.mark.parametrize("rule", sorted(CONNECT_RULES))
def test_connect_refuses_what_cannot_take_effect(rule: str, server: ServerThread) -> None:
    options, given = CONNECT_RULES[rule]
    before = threading.active_count()
    expected = str(refuse(rule, given))
    with pytest.raises(ValueError, match=re.escape(expected)) as info:
        Bridge.connect("127.0.0.1", server.port, **options)
    assert str(info.value) == expected
    assert threading.active_count() == before  # refused before any socket or thread
    assert server.server.registry is not None
    assert server.server.registry.ctx.counters.get("sessions_opened", 0) == 0


def test_every_rule_has_its_test() -> None:
    tested = {*OBJECT_RULES, *CONNECT_RULES, *(rule for rule, *_ in CALL_RULES.values())}
    assert tested == set(RULES)
    for row in RULES.values():  # each row reads as a sentence: where, what, why
        assert row.where, row
        assert row.option, row
        assert row.why[0].islower(), row


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
