"""The options several ``rlbridge`` commands share, defined once so they mean one thing.

:data:`SHORT_OPTIONS` is the only place a short option is given out: ``-H`` is ``--host`` in
every command that has a host (``serve`` and ``demo`` included), ``-t`` is ``--transport``
wherever there is a transport, and no command gives either letter another meaning
(``tests/cli/test_options.py`` walks every command to check). :func:`option` builds a
``typer.Option`` with the long name, its short one if it has one, and the help text.

The options that stand for the SDK's objects are defined here once and built into those
objects here only, so ``--help`` and the API cannot drift: ``ServerTarget`` (host, port,
``Tls``, ``Psk`` by :func:`psk_of`, which ``demo --psk-file`` calls too), ``ChannelChoice``
(``QoS`` and ``Policy``), and ``--idle``/``--bundles`` (``Tuning`` by :func:`tuning_of`,
which the bench's worker processes call with the options' text).
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import json
import logging
import re
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, TypeVar, cast

import typer

from rlbridge.cli.errors import fail

if TYPE_CHECKING:
    from pydantic import ValidationError

    from rlbridge.adapters.base import QoS
    from rlbridge.client.bridge import Bridge
    from rlbridge.client.options import Policy, Psk, Tls, Tuning

#: Long option -> its one short form, for every command.
SHORT_OPTIONS: dict[str, str] = {
    "--host": "-H",
    "--port": "-p",
    "--field": "-f",
    "--transport": "-t",
}

LOG_LEVELS = ("debug", "info", "warning", "error")
LOG_FORMAT = "%(asctime)s %(name)s %(levelname)s %(message)s"


def option(long: str, help: str, **kwargs: Any) -> Any:
    """``typer.Option(long, SHORT_OPTIONS[long], help=...)``; the short one only if it has one."""
    short = SHORT_OPTIONS.get(long)
    return typer.Option(long, *([short] if short else []), help=help, **kwargs)


def check_log_level(value: str | None) -> str | None:
    """A typer callback: one of :data:`LOG_LEVELS` (any case), else one error line, exit 2."""
    if value is None:
        return None
    if value.lower() not in LOG_LEVELS:
        raise fail(f"--log-level must be one of {', '.join(LOG_LEVELS)}, not '{value}'", 2)
    return value.lower()


def checked_transport(value: str) -> Literal["udp", "tcp"]:
    """``udp`` or ``tcp``, else a one-line usage error (exit 2); also ``--transport``'s
    callback, so a wrong one is refused before the command connects anywhere."""
    if value not in ("udp", "tcp"):
        raise fail(f"--transport must be 'udp' or 'tcp', not '{value}'", 2)
    return cast(Literal["udp", "tcp"], value)


class _CommandLog(logging.StreamHandler):  # type: ignore[type-arg]
    """The handler :func:`configure_logging` puts on the root logger (its type marks it ours)."""


def configure_logging(ctx: typer.Context, level: str) -> None:
    """Log to stderr at ``level`` until ``ctx`` closes; ``serve`` calls it again with its own.

    Undone when the command returns, not left behind: run in-process (typer's ``CliRunner``,
    a test), the handler would hold the runner's stderr, which it closes, and every later log
    line of the process would be a ``--- Logging error ---``.
    """
    ctx.with_resource(_logging_to_stderr(level))


@contextlib.contextmanager
def _logging_to_stderr(level: str) -> Iterator[None]:
    """Root logs to ``sys.stderr`` at ``level`` inside; after, its handlers and level as before.

    Only a handler of ours is taken off for the time (``serve``'s own level replaces the
    group's, one line per record); another one (an application's, pytest's) stays.
    """
    root = logging.getLogger()
    level_before = root.level
    ours = [h for h in root.handlers if isinstance(h, _CommandLog)]
    for h in ours:
        root.removeHandler(h)
    handler = _CommandLog(sys.stderr)
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    root.addHandler(handler)
    root.setLevel(level.upper())
    try:
        yield
    finally:
        root.removeHandler(handler)
        handler.close()
        for h in ours:
            root.addHandler(h)
        root.setLevel(level_before)


LOG_LEVEL_HELP = f"{', '.join(LOG_LEVELS)}."


def config_error(exc: ValidationError) -> str:
    """A config validation error in the command line's words: ``--timeout-ms``, not the
    config field ``timeout_ms`` (the message names the options a user typed)."""
    first = exc.errors()[0]
    fields = [str(p) for p in first["loc"]]
    message = str(first["msg"]).removeprefix("Value error, ")
    message = re.sub(r"\b([a-z]+(?:_[a-z]+)+)\b",
                     lambda m: "--" + m.group(1).replace("_", "-"), message)
    where = ", ".join("--" + f.replace("_", "-") for f in fields)
    return f"{where}: {message}" if where else message


# -- the options of every command that talks to a running server ------------------------
Host = Annotated[str, option("--host", "Bridge server address.")]
Port = Annotated[int, option("--port", "Bridge server port.")]
Field = Annotated[str, option("--field", "Field path ('data', 'linear.x'); '' = whole message.")]
TransportOpt = Annotated[str, option("--transport", "udp or tcp.", callback=checked_transport)]
TlsOpt = Annotated[bool, typer.Option("--tls", help="TLS, trusting the system's CAs.")]
CaOpt = Annotated[str | None, typer.Option("--ca", help="TLS, trusting this CA file.")]
FingerprintOpt = Annotated[str | None, typer.Option(
    "--fingerprint", help="TLS, pinning this certificate fingerprint (`rlbridge tls init`).")]
PskFileOpt = Annotated[str | None, typer.Option(
    "--psk-file", help="Pre-shared key file (the server's format); else $RLBRIDGE_PSK.")]
TlsCertOpt = Annotated[str | None, typer.Option(
    "--tls-cert", help="Mutual TLS: this client's certificate (PEM; with --tls-key).")]
TlsKeyOpt = Annotated[str | None, typer.Option(
    "--tls-key", help="The key of --tls-cert (PEM).")]


@dataclass(frozen=True)
class ServerTarget:
    """Where a command's session goes and how it proves itself: ``--host``, ``--port``,
    ``--tls``, ``--ca``, ``--fingerprint``, ``--tls-cert``/``--tls-key`` (mutual TLS, the
    server's option names), ``--psk-file``, the same in every command that talks to a running
    server (see :func:`server_options`)."""

    host: Host = "127.0.0.1"
    port: Port = 7411
    tls: TlsOpt = False
    ca: CaOpt = None
    fingerprint: FingerprintOpt = None
    tls_cert: TlsCertOpt = None
    tls_key: TlsKeyOpt = None
    psk_file: PskFileOpt = None

    def connect(self, name: str) -> Bridge:
        """One session named ``name``, no reconnect: a command does one thing and exits.

        ``--tls-cert`` and ``--tls-key`` go together (else a one-line usage error, exit 2)
        and, like ``--ca`` and ``--fingerprint``, turn TLS on.
        """
        from rlbridge.client.bridge import Bridge

        if (self.tls_cert is None) != (self.tls_key is None):
            raise fail("--tls-cert and --tls-key go together: give both for mutual TLS, or "
                       "neither", 2)
        client_cert = (None if self.tls_cert is None or self.tls_key is None
                       else (self.tls_cert, self.tls_key))
        return Bridge.connect(self.host, self.port, name=name, reconnect=False,
                              security=self.security(client_cert))

    def security(self, client_cert: tuple[str, str] | None = None) -> Psk | Tls | None:
        """The ``security=`` these options stand for, built here only: ``--psk-file`` is
        ``Psk(file=...)``; ``--tls``, ``--ca``, ``--fingerprint`` and a client certificate
        turn on ``Tls(...)`` (with the key inside it, if both are given)."""
        from rlbridge.client.options import Tls

        psk = psk_of(self.psk_file)
        if not (self.tls or self.ca or self.fingerprint or client_cert):
            return psk
        return Tls(ca=self.ca, fingerprint=self.fingerprint, client_cert=client_cert, psk=psk)


def psk_of(psk_file: str | Path | None) -> Psk | None:
    """``--psk-file``'s ``Psk(file=...)``, or None without one (``$RLBRIDGE_PSK`` then
    applies, as for ``security=None``): the one builder of every command with the option, the
    session commands (:meth:`ServerTarget.security`) and ``demo`` alike."""
    from rlbridge.client.options import Psk

    return None if psk_file is None else Psk(file=psk_file)


#: The ``server`` parameter's default, for calling a command function directly.
LOCAL_SERVER = ServerTarget()

F = TypeVar("F", bound=Callable[..., Any])


def _option_group(command: F, parameter: str, group: type[Any]) -> F:
    """Give ``command`` the fields of dataclass ``group`` as options, in place of its
    ``parameter``, which receives them as one ``group`` object."""
    hints = inspect.signature(group, eval_str=True).parameters
    added = [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY,
                               default=hints[name].default, annotation=hints[name].annotation)
             for name in (f.name for f in fields(group))]
    signature = inspect.signature(command, eval_str=True)
    own = [p for name, p in signature.parameters.items() if name != parameter]

    @functools.wraps(command)
    def with_group(*args: Any, **kwargs: Any) -> Any:
        value = group(**{p.name: kwargs.pop(p.name) for p in added})
        return command(*args, **{parameter: value}, **kwargs)

    with_group.__signature__ = signature.replace(  # type: ignore[attr-defined]
        parameters=[*own, *added])
    with_group.__annotations__ = {p.name: p.annotation for p in (*own, *added)}
    return cast(F, with_group)


def server_options(command: F) -> F:
    """Give ``command`` the :class:`ServerTarget` options in place of its ``server`` parameter.

    Typer reads a command's options from its signature, so each command listed host, port,
    TLS and key options and passed them on to ``Bridge.connect`` by hand (and the ``service``,
    ``param`` and ``action`` commands had drifted to host and port only). Here the options are
    the dataclass's fields, declared once; the command receives them as one ``ServerTarget``.
    """
    return _option_group(command, "server", ServerTarget)


# -- the options of every command that binds a topic: QoS and Policy, one to one ---------
ReliabilityOpt = Annotated[str | None, typer.Option(
    "--reliability", help="QoS reliability: reliable or best_effort (default: by transport, "
    "best effort for udp, reliable for tcp).")]
DepthOpt = Annotated[int, typer.Option("--depth", help="QoS history depth.")]
DurabilityOpt = Annotated[str, typer.Option(
    "--durability", help="QoS durability: volatile, transient_local (a latched topic) or "
    "match (subscribe: as the topic's publishers).")]
LatestOpt = Annotated[bool, typer.Option("--latest", help="Only the newest value matters: a "
                                         "backlog collapses to its newest value.")]
MaxAgeOpt = Annotated[int, typer.Option("--max-age-ms", help="Drop values older than this "
                                        "(0: no limit).")]
RedundancyOpt = Annotated[int, typer.Option("--redundancy", help="UDP: repeat the previous K "
                                            "values in each datagram (0..16).")]
FlowOpt = Annotated[bool | None, typer.Option("--flow/--no-flow", help="TCP: credit flow "
                                              "control, every value at the reader's pace "
                                              "(default: on where every value is promised).")]
MaxRateOpt = Annotated[float | None, typer.Option("--max-rate-hz", help="Publish: at most "
                                                  "this many values per second leave.")]
AdaptRateOpt = Annotated[bool, typer.Option("--adapt-rate", help="Publish, with --max-rate-hz: "
                                            "lower the rate while the server reports loss.")]
OnLostOpt = Annotated[str, typer.Option("--on-lost", help="Subscribe: "
                                        "reads while the link is lost: hold, raise, or a JSON "
                                        "safe value.")]


@dataclass(frozen=True)
class ChannelChoice:
    """A command's ``--reliability``/``--depth``/``--durability`` (one to one the fields of
    :class:`~rlbridge.QoS`) and ``--latest``, ``--max-age-ms``, ``--redundancy``,
    ``--flow``, ``--max-rate-hz``, ``--adapt-rate``, ``--on-lost`` (those of
    :class:`~rlbridge.Policy`), built into the SDK's objects here only (see
    :func:`channel_options`); the SDK's rules then refuse what a channel cannot honour."""

    reliability: ReliabilityOpt = None
    depth: DepthOpt = 10
    durability: DurabilityOpt = "volatile"
    latest: LatestOpt = False
    max_age_ms: MaxAgeOpt = 0
    redundancy: RedundancyOpt = 0
    flow: FlowOpt = None
    max_rate_hz: MaxRateOpt = None
    adapt_rate: AdaptRateOpt = False
    on_lost: OnLostOpt = "hold"

    def qos(self) -> QoS:
        """The :class:`~rlbridge.QoS` of these options (``ValueError`` naming a bad one)."""
        from rlbridge.adapters.base import QoS

        return QoS(cast(Any, self.reliability), self.depth, cast(Any, self.durability))

    def policy(self) -> Policy:
        """The :class:`~rlbridge.Policy` of these options (``ValueError`` naming a bad one)."""
        from rlbridge.client.channels.failsafe import SafeValue
        from rlbridge.client.options import Policy

        on_lost: str | SafeValue = self.on_lost
        if on_lost not in ("hold", "raise"):
            try:
                on_lost = SafeValue(json.loads(self.on_lost))
            except ValueError:
                raise ValueError(f"--on-lost must be 'hold', 'raise' or a JSON value (the safe "
                                 f"value), not '{self.on_lost}'") from None
        return Policy(latest=self.latest, max_age_ms=self.max_age_ms,
                      redundancy=self.redundancy, flow=self.flow, max_rate_hz=self.max_rate_hz,
                      adapt_rate=self.adapt_rate, on_lost=cast(Any, on_lost))


#: The ``channel`` parameter's default, for calling a command function directly.
DEFAULT_CHANNEL = ChannelChoice()


def channel_options(command: F) -> F:
    """Give ``command`` the :class:`ChannelChoice` options in place of its ``channel``
    parameter: every command that binds a topic takes the same QoS and policy options."""
    return _option_group(command, "channel", ChannelChoice)


# -- the SDK's Tuning, as far as a command reaches it: --idle and --bundles ---------------
IdleOpt = Annotated[str, typer.Option(
    "--idle", help="SDK idle strategies (park, spin, busy, comma-separated; send/receive for "
    "one per thread, e.g. park/spin): the rlbridge rows once per strategy, with CPU % per "
    "process and the publisher loop's lateness.")]
BundlesOpt = Annotated[bool, typer.Option(
    "--bundles/--no-bundles", help="Every channel of a session's tick in one datagram, both "
    "ways; --no-bundles: one datagram per value.")]


def idle_specs(text: str) -> tuple[str, ...]:
    """``--idle``'s comma-separated strategies, each checked by :func:`tuning_of` (a
    ``ValueError`` naming ``--idle`` and the choices for one that is not a strategy)."""
    specs = tuple(s.strip() for s in text.split(",") if s.strip())
    for spec in specs:
        tuning_of(idle=spec)
    return specs


def tuning_of(*, idle: str = "park", bundles: bool = True) -> Tuning:
    """The :class:`~rlbridge.Tuning` of one ``--idle`` strategy (``spin`` for both SDK
    threads, ``park/spin`` for the send and the receive thread) and ``--bundles``, built here
    only: the bench's worker processes get the options' text and call this too."""
    from rlbridge.client.options import Tuning
    from rlbridge.csp.idle import STRATEGIES

    parts = idle.split("/")
    unknown = [k for k in parts if k not in STRATEGIES]
    if unknown or len(parts) > 2:
        what = f"unknown idle strategy {unknown[0]!r}" if unknown else f"{idle!r}"
        raise ValueError(f"--idle: {what}; choose from {', '.join(STRATEGIES)} "
                         "(send/receive for one per thread)")
    return Tuning(idle=(parts[0], parts[1]) if len(parts) == 2 else idle, bundles=bundles)
