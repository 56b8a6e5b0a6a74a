"""Per-channel fail-safes: what an incoming channel's read does while the link is lost.

A control loop that reads its inputs without blocking keeps running when the link drops; what
it reads then is the channel's choice, made once at
``Bridge.subscribe(..., policy=Policy(on_lost=...))``:

``"hold"`` (default)
    Nothing changes: the newest value again (``channel.age_ns`` keeps growing, so the loop can
    judge it), and a blocking read keeps waiting, its timeout still applying, across a
    reconnect.
``SafeValue(v)``
    Every read returns ``v`` at once, blocking or not, until the link is back: the value that
    puts the actuator in a safe state. Values that arrive afterwards are read normally.
``"raise"``
    Every read raises :class:`LinkLost`, for code that must not act on old data.

Only channels with ``SafeValue`` or ``"raise"`` are a :class:`GuardedChannel` (an
:class:`~rlbridge.csp.bridge_channels.IncomingChannel` whose ``read`` checks first), so
``"hold"`` channels pay nothing. The check costs one attribute read per read (the Bridge's
``LinkEvents.lost``) and happens when the read starts: a blocking read already waiting when the
link drops keeps waiting (give it a timeout, or read without blocking from a hard-real-time
loop, which is the rule anyway).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, Protocol

from rlbridge.csp.bridge_channels import AgedValue, IncomingChannel
from rlbridge.errors import LinkLost


@dataclass(frozen=True, slots=True)
class SafeValue:
    """``Policy(on_lost=SafeValue(v))``: reads of the channel return ``v`` while the link is
    lost (the value that puts the actuator in a safe state), then real values again."""

    value: Any


#: What ``Policy(on_lost=...)`` accepts.
OnLost = Literal["hold", "raise"] | SafeValue


class LinkFlag(Protocol):
    """Whatever tells a fail-safe that the link is lost (``LinkEvents``)."""

    lost: bool


class FailSafe:
    """The ``SafeValue`` or ``"raise"`` policy of one channel, bound to the link's flag."""

    __slots__ = ("_flag", "_raise", "_value")

    def __init__(self, policy: SafeValue | Literal["raise"], flag: LinkFlag) -> None:
        self._flag = flag
        self._raise = policy == "raise"
        self._value = None if isinstance(policy, str) else policy.value

    @property
    def active(self) -> bool:
        """True while the link is lost: reads answer from here instead of the channel."""
        return self._flag.lost

    def read(self, channel_name: str) -> Any:
        if self._raise:
            raise LinkLost(channel_name)
        return self._value


class GuardedChannel(IncomingChannel):
    """An incoming channel with a fail-safe: reads answer from it while the link is lost."""

    __slots__ = ("failsafe",)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.failsafe: FailSafe | None = None  # set by Bridge.subscribe

    def read(self, timeout: float | None = None) -> Any:
        """Read as from any channel; while the link is lost, as ``on_lost`` says."""
        failsafe = self.failsafe
        if failsafe is not None and failsafe.active:
            return failsafe.read(self.name)
        return IncomingChannel.read(self, timeout)

    def read_with_age(self, timeout: float | None = None) -> AgedValue:
        """As :meth:`read`; a safe value has no stamp, so its age is -1."""
        failsafe = self.failsafe
        if failsafe is not None and failsafe.active:
            return AgedValue(failsafe.read(self.name), -1)
        return IncomingChannel.read_with_age(self, timeout)


def fail_safe(on_lost: OnLost, flag: LinkFlag) -> FailSafe | None:
    """The fail-safe for ``on_lost`` (``None`` for ``"hold"``: reads stay as they are)."""
    if on_lost == "hold":
        return None
    if on_lost == "raise" or isinstance(on_lost, SafeValue):
        return FailSafe(on_lost, flag)
    raise ValueError(f"on_lost must be 'hold', 'raise' or SafeValue(value), got {on_lost!r}")
