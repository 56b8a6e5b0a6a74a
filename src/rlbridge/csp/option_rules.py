"""No option is ignored: the combinations a call cannot honour, refused where they are made.

:class:`~rlbridge.csp.options.Policy`, :class:`~rlbridge.QoS`, :class:`~rlbridge.Psk`,
:class:`~rlbridge.Tls` and :class:`~rlbridge.Tuning` check what they can alone when they are
built; this module checks what depends on the call: the transport, the direction, blocking or
not. Each rule raises ``ValueError`` naming the option and why it cannot take effect, before
anything is sent (docs/api.md has the table; ``tests/client/test_option_rules.py`` one test
per rule). A rule is a line here, so a new option comes with its rule in the same place.
"""

from __future__ import annotations

from typing import Any

from rlbridge.adapters.base import QoS
from rlbridge.csp.options import Policy, Psk, Tls, Tuning
from rlbridge.csp.reconnect import Backoff


def _refuse(call: str, option: str, why: str) -> ValueError:
    return ValueError(f"{call}(): {option} {why}")


def _common(call: str, transport: str, qos: QoS, policy: Policy, buffer_size: int) -> None:
    if transport not in ("tcp", "udp"):
        raise _refuse(call, f"transport={transport!r}", "must be 'udp' or 'tcp'")
    if not isinstance(qos, QoS):
        raise _refuse(call, f"qos={qos!r}", "must be a QoS(...)")
    if not isinstance(policy, Policy):
        raise _refuse(call, f"policy={policy!r}", "must be a Policy(...)")
    if buffer_size < 1:
        raise _refuse(call, f"buffer_size={buffer_size}",
                      "is too small: a bridge channel needs buffer_size >= 1 (its ring holds at "
                      "least the newest value)")
    if qos.depth < 1:
        raise _refuse(call, f"QoS(depth={qos.depth})",
                      "is too small: depth must be >= 1 (the middleware keeps at least the "
                      "newest value)")
    if policy.redundancy and transport == "tcp":
        raise _refuse(call, f"Policy(redundancy={policy.redundancy})",
                      "repeats values in UDP datagrams; TCP already delivers every packet: "
                      "drop it, or use transport='udp'")
    if policy.flow and transport == "udp":
        raise _refuse(call, "Policy(flow=True)",
                      "needs transport='tcp': UDP drops values instead of waiting for credit")


def check_subscribe(transport: str, qos: QoS, policy: Policy, *, blocking: bool,
                    buffer_size: int, has_initial: bool) -> bool:
    """Refuse what ``subscribe`` cannot honour; return whether the channel is flow-controlled."""
    call = "subscribe"
    _common(call, transport, qos, policy, buffer_size)
    if has_initial and blocking:
        raise _refuse(call, "initial=",
                      "is what a non-blocking read returns before the first value; a "
                      "blocking read waits for a value instead: drop initial, or "
                      "blocking=False")
    if policy.max_rate_hz is not None or policy.adapt_rate:
        raise _refuse(call, "Policy(max_rate_hz=..., adapt_rate=...)",
                      "limits what a publisher sends; a subscriber cannot slow the topic's "
                      "publishers: use it on publish, or Policy(latest=True) to keep up")
    if policy.flow is None:
        return transport == "tcp" and not policy.latest and blocking
    return policy.flow


def check_publish(transport: str, qos: QoS, policy: Policy, *, buffer_size: int) -> bool:
    """Refuse what ``publish`` cannot honour; return whether the channel is flow-controlled."""
    call = "publish"
    _common(call, transport, qos, policy, buffer_size)
    if policy.on_lost != "hold":
        raise _refuse(call, f"Policy(on_lost={policy.on_lost!r})",
                      "is what reads of a subscribe channel do while the link is lost; "
                      "writes to a publish channel wait in its buffer (health() shows it)")
    if qos.durability == "match":
        raise _refuse(call, "QoS(durability='match')",
                      "copies the QoS of a topic's publishers into a subscription; a "
                      "publisher chooses: 'volatile' or 'transient_local' (latched)")
    if policy.flow is None:
        return transport == "tcp" and not policy.latest
    return policy.flow


def check_connect(security: Any, reconnect: Any, tuning: Any, *, nodelay: bool,
                  timeout: float, send_rate_hz: float | None) -> None:
    """Refuse what ``Bridge.connect`` cannot honour, before any socket is opened."""
    call = "Bridge.connect"
    if security is not None and not isinstance(security, Psk | Tls):
        raise _refuse(call, f"security={security!r}",
                      "must be Psk(key=... | file=...), Tls(...) or None ($RLBRIDGE_PSK if set)")
    if not isinstance(reconnect, bool | Backoff):
        raise _refuse(call, f"reconnect={reconnect!r}", "must be True, False or Backoff(...)")
    if not isinstance(tuning, Tuning):
        raise _refuse(call, f"tuning={tuning!r}", "must be a Tuning(...)")
    if not timeout > 0:
        raise _refuse(call, f"timeout={timeout}", "must be a positive number of seconds")
    if send_rate_hz is not None and not send_rate_hz > 0:
        raise _refuse(call, f"send_rate_hz={send_rate_hz}",
                      "must be positive (None: no send loop, values leave on write or send())")
    if tuning.control == "udp":
        if isinstance(security, Tls):
            raise _refuse(call, "security=Tls(...)",
                          "protects the TCP connection, and Tuning(control='udp') has none: "
                          "use Psk (it seals datagrams too), or control='tcp'")
        if nodelay:
            raise _refuse(call, "nodelay=True",
                          "turns off Nagle on the TCP connection, and Tuning(control='udp') "
                          "has none: drop it, or control='tcp'")
