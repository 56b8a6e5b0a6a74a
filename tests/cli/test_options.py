"""One meaning per short option across every ``rlbridge`` command (the class of ``-t`` being
--transport in one command and --show-types in another, or ``-H`` refused by serve)."""

from __future__ import annotations

import subprocess
import sys
import typing
from collections.abc import Iterator
from dataclasses import fields
from pathlib import Path
from typing import Any

import pytest
import typer

from rlbridge.cli.commands import build_app
from rlbridge.cli.options import SHORT_OPTIONS, ServerTarget


def _commands(group: Any, path: str = "rlbridge") -> Iterator[tuple[str, Any]]:
    """Every command and group under ``group`` (typer's click objects), with its path."""
    yield path, group
    for name, sub in getattr(group, "commands", {}).items():
        yield from _commands(sub, f"{path} {name}")


def _all() -> list[tuple[str, Any]]:
    return list(_commands(typer.main.get_command(build_app())))


def test_every_short_option_means_what_the_table_says() -> None:
    long_of = {short: long for long, short in SHORT_OPTIONS.items()}
    wrong = [
        f"{path}: {short} is {param.opts}, the table says {long_of.get(short)}"
        for path, command in _all() for param in command.params
        if param.param_type_name == "option"
        for short in param.opts + param.secondary_opts
        if not short.startswith("--") and long_of.get(short) not in param.opts
    ]
    assert wrong == []


def test_every_command_with_a_shared_option_also_has_its_short_form() -> None:
    """(The bench suites' own options keep their long names only: they are not tools a
    user types daily, and --transport there picks among more than udp and tcp.)"""
    missing = []
    for path, command in _all():
        if path.startswith("rlbridge bench"):
            continue
        for param in command.params:
            for long, short in SHORT_OPTIONS.items():
                if long in getattr(param, "opts", ()) and short not in param.opts:
                    missing.append(f"{path}: {long} without {short}")
    assert missing == []


def test_the_commands_a_user_meets_first_share_host_and_port() -> None:
    commands = dict(_all())
    for path in ("rlbridge serve", "rlbridge demo", "rlbridge stats", "rlbridge topic pub",
                 "rlbridge topic echo", "rlbridge topic hz", "rlbridge topic list"):
        opts = {o for p in commands[path].params for o in getattr(p, "opts", ())}
        assert {"--host", "-H", "--port", "-p"} <= opts, path
    for path in ("rlbridge serve", "rlbridge"):
        opts = {o for p in commands[path].params for o in getattr(p, "opts", ())}
        assert "--log-level" in opts, path


#: Every command that opens a session with a running server (``ping`` only probes: no key).
SESSION_COMMANDS = ("stats", "topic pub", "topic echo", "topic hz", "topic list",
                    "service list", "service call", "param get", "param set", "param list",
                    "action send")


def test_every_command_that_opens_a_session_takes_the_same_server_options() -> None:
    """One list (``ServerTarget``): TLS and the key file reach service, param and action too."""
    commands = dict(_all())
    wanted = {"--" + f.name.replace("_", "-") for f in fields(ServerTarget)}
    assert {"--host", "--port", "--tls", "--ca", "--fingerprint", "--psk-file"} <= wanted
    for path in SESSION_COMMANDS:
        opts = {o for p in commands[f"rlbridge {path}"].params for o in getattr(p, "opts", ())}
        assert wanted <= opts, f"{path}: lacks {sorted(wanted - opts)}"


# -- QoS and Policy: the same objects as the SDK's, built in one place --------------------
def test_the_channel_options_are_the_fields_of_qos_and_policy_one_to_one() -> None:
    """``--help`` and the API cannot drift: one option per field, the SDK's defaults."""
    from rlbridge import Policy, QoS
    from rlbridge.cli.options import DEFAULT_CHANNEL, ChannelChoice

    options = {f.name for f in fields(ChannelChoice)}
    assert options == {f.name for f in fields(QoS)} | {f.name for f in fields(Policy)}
    assert DEFAULT_CHANNEL.qos() == QoS()
    assert DEFAULT_CHANNEL.policy() == Policy()
    chosen = ChannelChoice(reliability="best_effort", depth=3, latest=True, max_age_ms=40,
                           on_lost="-1.5")
    assert chosen.qos() == QoS("best_effort", 3)
    assert chosen.policy().on_lost.value == -1.5  # type: ignore[union-attr]  # a SafeValue
    commands = dict(_all())
    wanted = {"--" + name.replace("_", "-") for name in options}
    for path in ("topic pub", "topic echo", "topic hz"):
        opts = {o for p in commands[f"rlbridge {path}"].params for o in getattr(p, "opts", ())}
        assert wanted <= opts, f"{path}: lacks {sorted(wanted - opts)}"


def _help_of(option: Any) -> str:
    """The help text an ``Annotated[..., typer.Option(...)]`` definition carries."""
    return str(typing.get_args(option)[1].help)


def _param(path: str, long: str) -> Any:
    found = [p for p in dict(_all())[path].params if long in getattr(p, "opts", ())]
    assert len(found) == 1, f"{path}: {long}"
    return found[0]


# -- --psk-file: one definition, one builder (the session commands and the demo) ----------
def test_every_client_side_psk_file_is_the_one_definition_built_by_psk_of(
        tmp_path: Path) -> None:
    """``demo --psk-file`` had its own option and built its ``Psk`` where it connected."""
    from rlbridge import Psk
    from rlbridge.cli.options import PskFileOpt, psk_of

    for path in (*(f"rlbridge {c}" for c in SESSION_COMMANDS), "rlbridge demo"):
        assert _param(path, "--psk-file").help == _help_of(PskFileOpt), path
    key = tmp_path / "key"
    assert psk_of(None) is None  # $RLBRIDGE_PSK then applies, as for security=None
    assert psk_of(key) == Psk(file=key)
    assert ServerTarget(psk_file=str(key)).security() == psk_of(str(key))


# -- --idle and --bundles: fields of Tuning, built in one place ---------------------------
def test_the_tuning_options_are_fields_of_tuning_and_build_it_in_one_place() -> None:
    """``bench latency --idle`` and ``bench load --bundles`` checked and built their
    ``Tuning`` in the bench's own code; now one definition each and :func:`tuning_of`."""
    from rlbridge import Tuning
    from rlbridge.cli.options import BundlesOpt, IdleOpt, idle_specs, tuning_of

    names = {f.name for f in fields(Tuning)}
    assert {"idle", "bundles"} <= names
    assert tuning_of() == Tuning()
    assert tuning_of(idle="spin", bundles=False) == Tuning(idle="spin", bundles=False)
    assert tuning_of(idle="park/busy") == Tuning(idle=("park", "busy"))
    for bad in ("nap", "park/nap", "/spin", "park/", "park/spin/busy", ""):
        with pytest.raises(ValueError, match=r"^--idle: .*choose from park, spin, busy"):
            tuning_of(idle=bad)
    assert idle_specs(" park, spin/park ,") == ("park", "spin/park")
    with pytest.raises(ValueError, match="--idle: unknown idle strategy 'nap'"):
        idle_specs("park,nap")
    assert _param("rlbridge bench latency", "--idle").help == _help_of(IdleOpt)
    bundles = _param("rlbridge bench load", "--bundles")
    assert bundles.help == _help_of(BundlesOpt)
    assert bundles.secondary_opts == ["--no-bundles"]


def test_a_wrong_idle_strategy_is_one_line_naming_the_option_before_anything_runs(
        tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "rlbridge", "bench", "latency", "--idle",
                           "park,nap"], capture_output=True, text=True, timeout=60, check=False,
                          cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr == ("rlbridge bench latency: error: --idle: unknown idle strategy 'nap'; "
                           "choose from park, spin, busy (send/receive for one per thread)\n")
