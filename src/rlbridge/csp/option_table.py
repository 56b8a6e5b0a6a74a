"""Every option rule, as data: what is refused, where, and why (one row per rule).

The option objects (:mod:`rlbridge.csp.options`) and the calls
(:mod:`rlbridge.csp.option_rules`) raise their ``ValueError`` from these rows, and docs/api.md
renders its table from them, so the error a user reads and the table cannot drift apart.
A message reads ``"<where>: <the option as given> <why>"``.
"""

from __future__ import annotations

from typing import NamedTuple


class Rule(NamedTuple):
    """One combination refused: ``where`` (the object or call), ``option`` (as the docs name
    it), ``why`` (the rest of the message: why it cannot take effect, what to do instead)."""

    where: str
    option: str
    why: str


RULES: dict[str, Rule] = {
    # -- the option objects, alone ------------------------------------------------------------
    "policy_max_age": Rule("Policy", "max_age_ms < 0", "must be >= 0 (0: no limit)"),
    "policy_redundancy": Rule("Policy", "redundancy outside 0..16",
                              "must be 0..16 previous values repeated in each datagram"),
    "policy_rate": Rule("Policy", "max_rate_hz <= 0", "must be positive (None: no limit)"),
    "policy_adapt": Rule("Policy", "adapt_rate=True without max_rate_hz",
                         "needs max_rate_hz: the rate it starts from and never exceeds"),
    "policy_flow_latest": Rule("Policy", "flow=True with latest=True",
                               "cannot both hold: a latest channel drops old values instead "
                               "of waiting for credit; choose one"),
    "policy_on_lost": Rule("Policy", "on_lost other than 'hold', 'raise', SafeValue(v)",
                           "must be 'hold', 'raise' or SafeValue(value)"),
    "setpoint_age": Rule("Policy.setpoint", "max_age_ms <= 0",
                         "is not positive: a set-point needs an age limit (how old a command "
                         "may be and still act)"),
    "qos_reliability": Rule("QoS", "reliability other than 'reliable', 'best_effort', None",
                            "must be 'reliable', 'best_effort' or None (by transport)"),
    "qos_durability": Rule("QoS", "durability not 'volatile', 'transient_local', 'match'",
                           "must be 'volatile', 'transient_local' or 'match'"),
    "psk_one": Rule("Psk", "both or neither of key= and file=",
                    "give exactly one, key= (hex or bytes) or file= (a key file)"),
    "tls_context": Rule("Tls", "context= with ca=, fingerprint= or client_cert=",
                        "context= is the whole TLS set-up: load the CA, pin and client "
                        "certificate into that context instead"),
    "tls_pin": Rule("Tls", "ca= with fingerprint=",
                    "a pinned fingerprint replaces the CA check, so the CA file would be "
                    "ignored; give one of them"),
    "tls_cert": Rule("Tls", "client_cert= not a pair",
                     "must be a (certificate file, key file) pair"),
    "tuning_control": Rule("Tuning", "control other than 'tcp', 'udp'", "must be 'tcp' or 'udp'"),
    "tuning_switch": Rule("Tuning", "switch_interval <= 0",
                          "must be a positive number of seconds (None: leave it alone)"),
    # -- publish and subscribe ----------------------------------------------------------------
    "transport": Rule("publish()/subscribe()", "transport other than 'udp', 'tcp'",
                      "must be 'udp' or 'tcp'"),
    "qos_type": Rule("publish()/subscribe()", "qos= not a QoS", "must be a QoS(...)"),
    "policy_type": Rule("publish()/subscribe()", "policy= not a Policy", "must be a Policy(...)"),
    "buffer_size": Rule("publish()/subscribe()", "buffer_size < 1",
                        "is too small: a bridge channel needs buffer_size >= 1 (its ring holds "
                        "at least the newest value)"),
    "depth": Rule("publish()/subscribe()", "QoS(depth < 1)",
                  "is too small: depth must be >= 1 (the middleware keeps at least the newest "
                  "value)"),
    "redundancy_tcp": Rule("publish()/subscribe()", "Policy(redundancy=k) with transport='tcp'",
                           "repeats values in UDP datagrams; TCP already delivers every packet: "
                           "drop it, or use transport='udp'"),
    "flow_udp": Rule("publish()/subscribe()", "Policy(flow=True) with transport='udp'",
                     "needs transport='tcp': UDP drops values instead of waiting for credit"),
    "initial_blocking": Rule("subscribe()", "initial= with blocking=True",
                             "is what a non-blocking read returns before the first value; a "
                             "blocking read waits for a value instead: drop initial, or "
                             "blocking=False"),
    "rate_subscribe": Rule("subscribe()", "Policy(max_rate_hz=..., adapt_rate=...)",
                           "limits what a publisher sends; a subscriber cannot slow the "
                           "topic's publishers: use it on publish, or Policy(latest=True) to "
                           "keep up"),
    "on_lost_publish": Rule("publish()", "Policy(on_lost=...) other than 'hold'",
                            "is what reads of a subscribe channel do while the link is lost; "
                            "writes to a publish channel wait in its buffer (health() shows "
                            "it)"),
    "adapt_tcp": Rule("publish()", "Policy(adapt_rate=True) with transport='tcp'",
                      "follows the loss the server reports at the first hop, and TCP loses "
                      "nothing there (it retransmits): use transport='udp', or max_rate_hz "
                      "alone"),
    "match_publish": Rule("publish()", "QoS(durability='match')",
                          "copies the QoS of a topic's publishers into a subscription; a "
                          "publisher chooses: 'volatile' or 'transient_local' (latched)"),
    # -- Bridge.connect -----------------------------------------------------------------------
    "security_type": Rule("Bridge.connect()", "security= not Psk, Tls or None",
                          "must be Psk(key=... | file=...), Tls(...) or None ($RLBRIDGE_PSK "
                          "if set)"),
    "reconnect_type": Rule("Bridge.connect()", "reconnect= not a bool or Backoff",
                           "must be True, False or Backoff(...)"),
    "tuning_type": Rule("Bridge.connect()", "tuning= not a Tuning", "must be a Tuning(...)"),
    "timeout": Rule("Bridge.connect()", "timeout <= 0", "must be a positive number of seconds"),
    "send_rate": Rule("Bridge.connect()", "send_rate_hz <= 0",
                      "must be positive (None: no send loop, values leave on write or send())"),
    "tls_udp": Rule("Bridge.connect()", "security=Tls(...) with Tuning(control='udp')",
                    "protects the TCP connection, and Tuning(control='udp') has none: use Psk "
                    "(it seals datagrams too), or control='tcp'"),
    "nodelay_udp": Rule("Bridge.connect()", "nodelay=True with Tuning(control='udp')",
                        "turns off Nagle on the TCP connection, and Tuning(control='udp') has "
                        "none: drop it, or control='tcp'"),
}


def refuse(rule: str, given: str, where: str | None = None) -> ValueError:
    """The error of ``rule``, naming the option as the caller gave it (``given``);
    ``where`` replaces the row's (``publish()`` for a rule shared with ``subscribe()``)."""
    row = RULES[rule]
    return ValueError(f"{where or row.where}: {given} {row.why}")
