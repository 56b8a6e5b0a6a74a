"""rlbridge: a bridge between hard-real-time control code and ROS 2, over TCP and UDP.

Everything a program needs comes from here (``from rlbridge import Bridge, QoS, Policy``):

* the SDK: :class:`Bridge` (``Bridge.connect(host, port)``, then ``subscribe``/``publish``
  return channels bound to topics) and its option objects :class:`QoS` (the middleware's side),
  :class:`Policy` (the network's), :class:`Psk`/:class:`Tls` (security), :class:`Backoff`
  (reconnect), :class:`Tuning` (threads and sockets), :class:`SafeValue` (fail-safe);
* the channels and what they report: :class:`IncomingChannel`, :class:`OutgoingChannel`,
  :class:`Channel` (local CSP channels, ``Channel()`` a rendezvous), :class:`ChannelHealth`,
  :class:`ChannelStatistics`, :class:`LinkState`, :class:`LinkEvent`;
* CSP processes and time: :class:`Process`, :class:`Code`, :class:`Sequential`,
  :class:`Parallel`, :class:`PriParallel`, :class:`Recursion`, :class:`PeriodicTimer`,
  :class:`Timed`;
* the hard-real-time coupling patterns (``receive_nonblocking``, ``send_loop``, ...) and the
  HRT process helpers (:class:`HrtProcess`, :class:`ShmLink`, :func:`forwarder`);
* every exception, rooted at :class:`RlbridgeError` (also :mod:`rlbridge.errors`).

The server is the command ``rlbridge serve``, or :mod:`rlbridge.server` to embed one;
``rlbridge --help`` lists every command. The distribution is ``rlbridge-sdk``. Importing this
package imports neither asyncio's server machinery nor rclpy: each name loads on first use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from rlbridge import _compiled  # noqa: F401  (first: it decides how the compiled modules load)
from rlbridge._version import __version__

if TYPE_CHECKING:
    from rlbridge.adapters.base import QoS
    from rlbridge.csp.bridge import Bridge
    from rlbridge.csp.bridge_channels import AgedValue, IncomingChannel, OutgoingChannel
    from rlbridge.csp.channel import Channel
    from rlbridge.csp.coupling import BaseCoupling, ControlLoop, Coupling, LoopOptions, Pump, Ticker
    from rlbridge.csp.failsafe import SafeValue
    from rlbridge.csp.gil import (
        HRT_SWITCH_INTERVAL,
        realtime_switch_interval,
        shorter_switch_interval,
    )
    from rlbridge.csp.health import ChannelHealth
    from rlbridge.csp.idle import IdleStrategy
    from rlbridge.csp.isolated import DEFAULT_LAYOUT, IsolatedCoupling
    from rlbridge.csp.link_events import LinkEvent
    from rlbridge.csp.options import Policy, Psk, Tls, Tuning
    from rlbridge.csp.patterns import (
        receive_blocking,
        receive_naive,
        receive_nonblocking,
        reference,
        send_buffered,
        send_loop,
        send_naive,
        send_sampled,
    )
    from rlbridge.csp.process import Code, Parallel, PriParallel, Process, Recursion, Sequential
    from rlbridge.csp.reconnect import Backoff
    from rlbridge.csp.rtenv import prepare_hrt_process, thread_scheduling
    from rlbridge.csp.shm import HrtProcess, ShmLink, forwarder
    from rlbridge.csp.statistics import ChannelStatistics
    from rlbridge.csp.timer import PeriodicTimer, Timed
    from rlbridge.errors import (
        AuthenticationFailed,
        BadValueError,
        BindingRefused,
        ChannelClosed,
        ChannelError,
        ChannelMisuseError,
        ConnectionClosed,
        ConnectionFailed,
        ErrorCode,
        GoalRejected,
        LimitExceeded,
        LinkLost,
        LocalProtocolError,
        NoCipher,
        NoServiceError,
        NoSuchFieldError,
        NoValueYet,
        ParameterError,
        ProtocolError,
        RealTimeWarning,
        RemoteError,
        RemoteProtocolError,
        RlbridgeError,
        SecondWriterError,
        ServerShuttingDown,
        ServiceError,
        ServiceFailed,
        ServiceTimeout,
        SessionError,
        TlsError,
        TlsFailed,
        TypeClashError,
        UnknownTypeError,
        ValueRejected,
        WouldBlock,
        WrongValueType,
    )
    from rlbridge.wire.link import LinkState

#: Each public name and the module that defines it (loaded on first use).
_HOMES: dict[str, str] = {
    'Bridge': 'rlbridge.csp.bridge',
    'QoS': 'rlbridge.adapters.base',
    'Policy': 'rlbridge.csp.options',
    'Psk': 'rlbridge.csp.options',
    'Tls': 'rlbridge.csp.options',
    'Tuning': 'rlbridge.csp.options',
    'Backoff': 'rlbridge.csp.reconnect',
    'SafeValue': 'rlbridge.csp.failsafe',
    'LinkState': 'rlbridge.wire.link',
    'LinkEvent': 'rlbridge.csp.link_events',
    'IncomingChannel': 'rlbridge.csp.bridge_channels',
    'OutgoingChannel': 'rlbridge.csp.bridge_channels',
    'AgedValue': 'rlbridge.csp.bridge_channels',
    'ChannelHealth': 'rlbridge.csp.health',
    'ChannelStatistics': 'rlbridge.csp.statistics',
    'Channel': 'rlbridge.csp.channel',
    'Process': 'rlbridge.csp.process',
    'Code': 'rlbridge.csp.process',
    'Sequential': 'rlbridge.csp.process',
    'Parallel': 'rlbridge.csp.process',
    'PriParallel': 'rlbridge.csp.process',
    'Recursion': 'rlbridge.csp.process',
    'PeriodicTimer': 'rlbridge.csp.timer',
    'Timed': 'rlbridge.csp.timer',
    'IdleStrategy': 'rlbridge.csp.idle',
    'ControlLoop': 'rlbridge.csp.coupling',
    'Coupling': 'rlbridge.csp.coupling',
    'BaseCoupling': 'rlbridge.csp.coupling',
    'LoopOptions': 'rlbridge.csp.coupling',
    'Ticker': 'rlbridge.csp.coupling',
    'Pump': 'rlbridge.csp.coupling',
    'IsolatedCoupling': 'rlbridge.csp.isolated',
    'DEFAULT_LAYOUT': 'rlbridge.csp.isolated',
    'reference': 'rlbridge.csp.patterns',
    'receive_nonblocking': 'rlbridge.csp.patterns',
    'receive_blocking': 'rlbridge.csp.patterns',
    'receive_naive': 'rlbridge.csp.patterns',
    'send_naive': 'rlbridge.csp.patterns',
    'send_buffered': 'rlbridge.csp.patterns',
    'send_sampled': 'rlbridge.csp.patterns',
    'send_loop': 'rlbridge.csp.patterns',
    'HrtProcess': 'rlbridge.csp.shm',
    'ShmLink': 'rlbridge.csp.shm',
    'forwarder': 'rlbridge.csp.shm',
    'HRT_SWITCH_INTERVAL': 'rlbridge.csp.gil',
    'shorter_switch_interval': 'rlbridge.csp.gil',
    'realtime_switch_interval': 'rlbridge.csp.gil',
    'prepare_hrt_process': 'rlbridge.csp.rtenv',
    'thread_scheduling': 'rlbridge.csp.rtenv',
    'RlbridgeError': 'rlbridge.errors',
    'RealTimeWarning': 'rlbridge.errors',
    'SessionError': 'rlbridge.errors',
    'ConnectionFailed': 'rlbridge.errors',
    'ConnectionClosed': 'rlbridge.errors',
    'AuthenticationFailed': 'rlbridge.errors',
    'TlsError': 'rlbridge.errors',
    'TlsFailed': 'rlbridge.errors',
    'NoCipher': 'rlbridge.errors',
    'ServerShuttingDown': 'rlbridge.errors',
    'ChannelError': 'rlbridge.errors',
    'ChannelClosed': 'rlbridge.errors',
    'WouldBlock': 'rlbridge.errors',
    'NoValueYet': 'rlbridge.errors',
    'ChannelMisuseError': 'rlbridge.errors',
    'SecondWriterError': 'rlbridge.errors',
    'LinkLost': 'rlbridge.errors',
    'BindingRefused': 'rlbridge.errors',
    'UnknownTypeError': 'rlbridge.errors',
    'TypeClashError': 'rlbridge.errors',
    'NoSuchFieldError': 'rlbridge.errors',
    'ValueRejected': 'rlbridge.errors',
    'WrongValueType': 'rlbridge.errors',
    'BadValueError': 'rlbridge.errors',
    'LimitExceeded': 'rlbridge.errors',
    'ServiceError': 'rlbridge.errors',
    'NoServiceError': 'rlbridge.errors',
    'ServiceTimeout': 'rlbridge.errors',
    'ServiceFailed': 'rlbridge.errors',
    'GoalRejected': 'rlbridge.errors',
    'ParameterError': 'rlbridge.errors',
    'RemoteError': 'rlbridge.errors',
    'ProtocolError': 'rlbridge.errors',
    'LocalProtocolError': 'rlbridge.errors',
    'RemoteProtocolError': 'rlbridge.errors',
    'ErrorCode': 'rlbridge.errors',
}

__all__ = [
    'AgedValue',
    'AuthenticationFailed',
    'Backoff',
    'BadValueError',
    'BaseCoupling',
    'BindingRefused',
    'Bridge',
    'Channel',
    'ChannelClosed',
    'ChannelError',
    'ChannelHealth',
    'ChannelMisuseError',
    'ChannelStatistics',
    'Code',
    'ConnectionClosed',
    'ConnectionFailed',
    'ControlLoop',
    'Coupling',
    'DEFAULT_LAYOUT',
    'ErrorCode',
    'GoalRejected',
    'HRT_SWITCH_INTERVAL',
    'HrtProcess',
    'IdleStrategy',
    'IncomingChannel',
    'IsolatedCoupling',
    'LimitExceeded',
    'LinkEvent',
    'LinkLost',
    'LinkState',
    'LocalProtocolError',
    'LoopOptions',
    'NoCipher',
    'NoServiceError',
    'NoSuchFieldError',
    'NoValueYet',
    'OutgoingChannel',
    'Parallel',
    'ParameterError',
    'PeriodicTimer',
    'Policy',
    'PriParallel',
    'Process',
    'ProtocolError',
    'Psk',
    'Pump',
    'QoS',
    'RealTimeWarning',
    'Recursion',
    'RemoteError',
    'RemoteProtocolError',
    'RlbridgeError',
    'SafeValue',
    'SecondWriterError',
    'Sequential',
    'ServerShuttingDown',
    'ServiceError',
    'ServiceFailed',
    'ServiceTimeout',
    'SessionError',
    'ShmLink',
    'Ticker',
    'Timed',
    'Tls',
    'TlsError',
    'TlsFailed',
    'Tuning',
    'TypeClashError',
    'UnknownTypeError',
    'ValueRejected',
    'WouldBlock',
    'WrongValueType',
    'forwarder',
    'prepare_hrt_process',
    'realtime_switch_interval',
    'receive_blocking',
    'receive_naive',
    'receive_nonblocking',
    'reference',
    'send_buffered',
    'send_loop',
    'send_naive',
    'send_sampled',
    'shorter_switch_interval',
    'thread_scheduling',
    '__version__',
]


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'rlbridge' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value  # the next access is a plain module attribute
    return value


def __dir__() -> list[str]:
    """The lazy names too, so ``dir(rlbridge)`` and completion show ``Bridge``."""
    return sorted({*globals(), *__all__})
