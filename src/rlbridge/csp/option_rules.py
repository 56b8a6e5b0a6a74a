"""No option is ignored: the combinations a call cannot honour, refused where they are made.

:class:`~rlbridge.csp.options.Policy`, :class:`~rlbridge.QoS`, :class:`~rlbridge.Psk`,
:class:`~rlbridge.Tls` and :class:`~rlbridge.Tuning` check what they can alone when they are
built; this module checks what depends on the call: the transport, the direction, blocking or
not. Each rule raises ``ValueError`` naming the option and why it cannot take effect, before
anything is sent. The words of every rule are a row of :data:`~rlbridge.csp.option_table.RULES`
(docs/api.md renders its table from them; ``tests/client/test_option_rules.py`` has a test per
rule), so a new option comes with its row, its check here and its test.
"""

from __future__ import annotations

from typing import Any

from rlbridge.adapters.base import QoS
from rlbridge.csp.option_table import refuse
from rlbridge.csp.options import Policy, Psk, Tls, Tuning
from rlbridge.csp.reconnect import Backoff


def _common(call: str, transport: str, qos: QoS, policy: Policy, buffer_size: int) -> None:
    if transport not in ("tcp", "udp"):
        raise refuse("transport", f"transport={transport!r}", call)
    if not isinstance(qos, QoS):
        raise refuse("qos_type", f"qos={qos!r}", call)
    if not isinstance(policy, Policy):
        raise refuse("policy_type", f"policy={policy!r}", call)
    if buffer_size < 1:
        raise refuse("buffer_size", f"buffer_size={buffer_size}", call)
    if qos.depth < 1:
        raise refuse("depth", f"QoS(depth={qos.depth})", call)
    if policy.redundancy and transport == "tcp":
        raise refuse("redundancy_tcp", f"Policy(redundancy={policy.redundancy})", call)
    if policy.flow and transport == "udp":
        raise refuse("flow_udp", "Policy(flow=True)", call)


def check_subscribe(transport: str, qos: QoS, policy: Policy, *, blocking: bool,
                    buffer_size: int, has_initial: bool) -> bool:
    """Refuse what ``subscribe`` cannot honour; return whether the channel is flow-controlled."""
    _common("subscribe()", transport, qos, policy, buffer_size)
    if has_initial and blocking:
        raise refuse("initial_blocking", "initial=")
    if policy.max_rate_hz is not None or policy.adapt_rate:
        raise refuse("rate_subscribe", "Policy(max_rate_hz=..., adapt_rate=...)")
    if policy.flow is None:
        return transport == "tcp" and not policy.latest and blocking
    return policy.flow


def check_publish(transport: str, qos: QoS, policy: Policy, *, buffer_size: int) -> bool:
    """Refuse what ``publish`` cannot honour; return whether the channel is flow-controlled."""
    _common("publish()", transport, qos, policy, buffer_size)
    if policy.on_lost != "hold":
        raise refuse("on_lost_publish", f"Policy(on_lost={policy.on_lost!r})")
    if policy.adapt_rate and transport == "tcp":
        raise refuse("adapt_tcp", "Policy(adapt_rate=True)")
    if qos.durability == "match":
        raise refuse("match_publish", "QoS(durability='match')")
    if policy.flow is None:
        return transport == "tcp" and not policy.latest
    return policy.flow


def check_connect(security: Any, reconnect: Any, tuning: Any, *, nodelay: bool,
                  timeout: float, send_rate_hz: float | None) -> None:
    """Refuse what ``Bridge.connect`` cannot honour, before any socket is opened."""
    if security is not None and not isinstance(security, Psk | Tls):
        raise refuse("security_type", f"security={security!r}")
    if not isinstance(reconnect, bool | Backoff):
        raise refuse("reconnect_type", f"reconnect={reconnect!r}")
    if not isinstance(tuning, Tuning):
        raise refuse("tuning_type", f"tuning={tuning!r}")
    if not timeout > 0:
        raise refuse("timeout", f"timeout={timeout}")
    if send_rate_hz is not None and not send_rate_hz > 0:
        raise refuse("send_rate", f"send_rate_hz={send_rate_hz}")
    if tuning.control == "udp":
        if isinstance(security, Tls):
            raise refuse("tls_udp", "security=Tls(...)")
        if nodelay:
            raise refuse("nodelay_udp", "nodelay=True")
