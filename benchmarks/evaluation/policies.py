"""Channel-policy rows of the evaluation, run only when this build's SDK has the policy.

The policies (latest-value delivery, redundancy ``k`` on UDP, a maximum age with
``IncomingChannel.read_with_age``, ``channel.health()``) are added to the SDK separately from
this harness. Whether a build has them is read from the fields of ``rlbridge.Policy``, not
guessed from an exception: a row whose option ``Policy`` does not have is reported as
"not available in this build" and not run, while a row that runs and fails is an error.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class PolicyRow:
    """One policy variant of the down stream: transport, ``Policy`` options, label."""

    key: str
    label: str
    transport: str
    nodelay: bool
    policy: dict[str, Any] = field(default_factory=dict)
    age_limit_ms: float | None = None
    #: Methods of ``IncomingChannel`` the row needs besides the keyword arguments.
    methods: tuple[str, ...] = ()


def policy_rows(delay_ms: float) -> list[PolicyRow]:
    """The rows asked for at one scenario; the age limit is the link delay plus 10 ms."""
    limit = delay_ms + 10.0
    return [
        PolicyRow("tcpn-latest", "TCPn + latest", "tcp", True, {"latest": True}),
        PolicyRow("udp-k1", "UDP + redundancy k=1", "udp", False, {"redundancy": 1}),
        PolicyRow("udp-k2", "UDP + redundancy k=2", "udp", False, {"redundancy": 2}),
        PolicyRow("tcp-maxage", f"TCP+Nagle, age > {limit:g} ms flagged (read_with_age)", "tcp",
                  False, age_limit_ms=limit, methods=("read_with_age",)),
        PolicyRow("tcp-maxage-drop", f"TCP+Nagle + max_age_ms={math.ceil(limit)} (drop: "
                  "counted as lost)", "tcp", False, {"max_age_ms": math.ceil(limit)}),
        PolicyRow("udp-maxage", f"UDP, age > {limit:g} ms flagged (read_with_age)", "udp", False,
                  age_limit_ms=limit, methods=("read_with_age",)),
    ]


def missing_features(row: PolicyRow, policy: type | None = None,
                     channel: type | None = None) -> list[str]:
    """What this build (or the given ``Policy``/``IncomingChannel`` classes) lacks for ``row``."""
    if policy is None or channel is None:
        from rlbridge import IncomingChannel, Policy

        policy, channel = policy or Policy, channel or IncomingChannel
    options = {f.name for f in dataclasses.fields(policy)}
    missing = [f"Policy({k}=...)" for k in row.policy if k not in options]
    missing += [f"IncomingChannel.{m}()" for m in row.methods
                if not callable(getattr(channel, m, None))]
    return missing


def availability(row: PolicyRow, policy: type | None = None,
                 channel: type | None = None) -> str | None:
    """None when ``row`` can run here, else the reason printed in its table row."""
    missing = missing_features(row, policy, channel)
    return f"not available in this build (no {', '.join(missing)})" if missing else None


def has_health() -> bool:
    """Whether incoming channels report ``health()`` (RTT, jitter, loss per channel)."""
    from rlbridge.csp.bridge_channels import IncomingChannel

    return callable(getattr(IncomingChannel, "health", None))
