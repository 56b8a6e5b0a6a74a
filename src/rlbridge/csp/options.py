"""The grouped options of :class:`~rlbridge.Bridge`: one small frozen object per kind of choice.

A call takes at most a handful of keywords because the options come in groups, each one object
a program builds once and reuses (as rclpy passes one ``QoSProfile``):

* :class:`Policy` (``publish``/``subscribe``): what the network does with a channel's values,
  with the two presets the docs teach, :meth:`Policy.setpoint` and :meth:`Policy.every_value`;
* :class:`~rlbridge.QoS` (``publish``/``subscribe``): the middleware's side, reused from the
  adapters (``rlbridge.adapters.base``);
* :class:`Psk` or :class:`Tls` (``connect(security=...)``): how the session is protected;
* :class:`Tuning` (``connect``): the rarely touched knobs of the SDK's threads and sockets.

Each object checks what it can alone when it is made (``ValueError`` naming the option); what
depends on the call (a transport, a direction) is checked by :mod:`rlbridge.csp.option_rules`.
"""

from __future__ import annotations

import ssl
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from rlbridge.csp.failsafe import OnLost, SafeValue
from rlbridge.csp.idle import IdleSpec
from rlbridge.csp.option_table import refuse
from rlbridge.csp.session_owner import Control


@dataclass(frozen=True, slots=True)
class Policy:
    """What the network does with one channel's values (docs/policies.md); frozen, reusable.

    ``latest``: only the newest value matters: a backlog (after a stall or a TCP
    retransmission) collapses to its newest value. ``max_age_ms``: values older than that are
    dropped, before sending and on arrival (0: no limit). ``redundancy=k`` (UDP only): each
    datagram repeats the previous k values, so one lost datagram loses no value.
    ``flow`` (TCP only, not with ``latest``): credit flow control, every value end to end at
    the reader's pace; ``None`` turns it on where every value is promised (TCP, not latest:
    every publish channel, and blocking subscribe channels). ``max_rate_hz`` (publish only):
    at most that many values per second leave, the rest wait in the buffer; ``adapt_rate``
    (with ``max_rate_hz``) lowers the rate while the server reports first-hop loss.
    ``on_lost`` (subscribe only): what reads do while the link is lost: ``"hold"`` the last
    value, ``"raise"`` :class:`~rlbridge.LinkLost`, or return ``SafeValue(v)``.

    Combinations that cannot take effect raise ``ValueError`` here or at the call.
    """

    latest: bool = False
    max_age_ms: int = 0
    redundancy: int = 0
    flow: bool | None = None
    max_rate_hz: float | None = None
    adapt_rate: bool = False
    on_lost: OnLost = "hold"

    def __post_init__(self) -> None:
        if self.max_age_ms < 0:
            raise refuse("policy_max_age", f"max_age_ms={self.max_age_ms}")
        if not 0 <= self.redundancy <= 16:
            raise refuse("policy_redundancy", f"redundancy={self.redundancy}")
        if self.max_rate_hz is not None and not self.max_rate_hz > 0:
            raise refuse("policy_rate", f"max_rate_hz={self.max_rate_hz}")
        if self.adapt_rate and self.max_rate_hz is None:
            raise refuse("policy_adapt", "adapt_rate=True")
        if self.flow and self.latest:
            raise refuse("policy_flow_latest", "flow=True, latest=True")
        if not (self.on_lost in ("hold", "raise") or isinstance(self.on_lost, SafeValue)):
            raise refuse("policy_on_lost", f"on_lost={self.on_lost!r}")

    @classmethod
    def setpoint(cls, *, max_age_ms: int, on_lost: OnLost = "hold") -> Policy:
        """A set-point or command: the newest value wins, values older than ``max_age_ms``
        are dropped, and (on a subscribe channel) reads while the link is lost do what
        ``on_lost`` says, e.g. ``SafeValue(0.0)`` to stop an actuator."""
        if max_age_ms <= 0:
            raise refuse("setpoint_age", f"max_age_ms={max_age_ms}")
        return cls(latest=True, max_age_ms=max_age_ms, on_lost=on_lost)

    @classmethod
    def every_value(cls) -> Policy:
        """Nothing lost: credit flow control end to end (a TCP channel; on subscribe, a
        blocking one), the writer paced by the slowest reader (``wait_writable``)."""
        return cls(flow=True)


@dataclass(frozen=True, slots=True)
class Psk:
    """A pre-shared key (docs/security.md): ``key`` in hex (``openssl rand -hex 32``) or as
    bytes, or ``file``: a key file in the server's format (this client's ``name`` line, else
    the default line). Exactly one of the two."""

    key: bytes | str | None = None
    file: str | Path | None = None

    def __post_init__(self) -> None:
        if (self.key is None) == (self.file is None):
            raise refuse("psk_one", "key= and file= both given:" if self.key is not None
                         else "neither key= nor file= given:")


@dataclass(frozen=True, slots=True)
class Tls:
    """TLS 1.3 for the session (docs/security.md).

    ``Tls()`` verifies the server against the system's CAs; ``ca=`` against a CA file;
    ``fingerprint=`` pins exactly one certificate by its SHA-256 (``rlbridge tls init`` prints
    it; replaces the CA check); ``client_cert=(cert, key)`` for a server that requires client
    certificates; ``context=`` an ``ssl.SSLContext`` of your own, instead of the three.
    ``psk=Psk(...)``: authenticate the client with a key as well, the key handshake running
    inside TLS (without it, ``$RLBRIDGE_PSK`` if set, as for ``security=None``).
    """

    ca: str | Path | None = None
    fingerprint: str | None = None
    client_cert: tuple[str | Path, str | Path] | None = None
    context: ssl.SSLContext | None = None
    psk: Psk | None = None

    def __post_init__(self) -> None:
        if self.context is not None and (self.ca or self.fingerprint or self.client_cert):
            raise refuse("tls_context", "context= with ca=, fingerprint= or client_cert=:")
        if self.ca is not None and self.fingerprint is not None:
            raise refuse("tls_pin", "ca= with fingerprint=:")
        if self.client_cert is not None and len(self.client_cert) != 2:
            raise refuse("tls_cert", f"client_cert={self.client_cert!r}")


Idle = IdleSpec | tuple[IdleSpec, IdleSpec]


@dataclass(frozen=True, slots=True)
class Tuning:
    """The rarely touched knobs of a session (``Bridge.connect(tuning=Tuning(...))``).

    ``control="udp"`` for a server started with ``--no-tcp`` (no TCP connection at all: no TLS,
    no ``nodelay``). ``bundles=False``: a datagram per UDP channel, not one bundle per round
    (protocol.md 6.16). ``idle``: how the send and receive threads (and blocking reads) wait:
    ``"park"``, ``"spin"`` (poll 20 us, yield 200 us, park), ``"busy"``, an ``IdleStrategy``
    or a ``(send, receive)`` pair (docs/concepts.md). ``switch_interval``: shorten CPython's
    GIL switch interval to this many seconds (never lengthen it) so a control loop waking
    while another thread computes waits at most that long (docs/gil.md); ``None`` leaves it.
    """

    control: Control = "tcp"
    bundles: bool = True
    idle: Idle = "park"
    switch_interval: float | None = None

    def __post_init__(self) -> None:
        if self.control not in ("tcp", "udp"):
            raise refuse("tuning_control", f"control={self.control!r}")
        if self.switch_interval is not None and not self.switch_interval > 0:
            raise refuse("tuning_switch", f"switch_interval={self.switch_interval}")


Security = Psk | Tls | None
"""What ``Bridge.connect(security=...)`` takes (``None``: ``$RLBRIDGE_PSK`` if set, else plain)."""

Transport = Literal["tcp", "udp"]
"""Per channel: ``udp`` when the newest value matters most, ``tcp`` when every value must arrive."""
