"""``rlbridge service``, ``param`` and ``action``: the ``ros2`` command's verbs, through a server.

Each command opens one session (the server options of ``topic`` and ``stats``: ``--host``,
``--port``, ``--tls``, ``--ca``, ``--fingerprint``, ``--psk-file``, else ``$RLBRIDGE_PSK``),
does one thing and prints JSON, so scripts can read it. Requests, goals and
parameter values are JSON or YAML flow style (``'{data: true}'``, as ``ros2 service call``
takes them); YAML needs PyYAML (part of the ``ros2`` extra).
"""

from __future__ import annotations

import json
from typing import Annotated, Any

import typer

from rlbridge.cli_errors import fail, one_line_errors
from rlbridge.cli_options import LOCAL_SERVER, ServerTarget, option, server_options

service_app = typer.Typer(help="Call and list services through a running server.",
                          no_args_is_help=True)
param_app = typer.Typer(help="Get, set and list the parameters of ROS nodes.",
                        no_args_is_help=True)
action_app = typer.Typer(help="Send action goals through a running server.",
                         no_args_is_help=True)

Timeout = Annotated[float, option("--timeout", "Seconds to wait for the answer.")]


def parse_document(text: str, what: str) -> Any:
    """JSON, else YAML (flow style, like ``ros2``): ``'{data: true}'``."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        pass
    try:
        import yaml
    except ImportError:
        raise fail(f"{what} is not JSON ({text!r}); for YAML install PyYAML") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise fail(f"{what} is neither JSON nor YAML: {str(exc).splitlines()[0]}") from None


def _fields(text: str, what: str) -> dict[str, Any]:
    parsed = parse_document(text, what) if text.strip() else {}
    if parsed is None:
        return {}
    if not isinstance(parsed, dict):
        raise fail(f"{what} must be a mapping of fields, like '{{data: true}}', not {text!r}")
    return parsed


@service_app.command("list")
@one_line_errors
@server_options
def service_list(
    server: ServerTarget = LOCAL_SERVER,
    show_types: Annotated[bool, option("--show-types", "Print types too.")] = False,
) -> None:
    """List the services the server's middleware knows."""
    with server.connect("rlbridge-service-list") as bridge:
        for name, srv_type in bridge.service_list():
            typer.echo(f"{name} [{srv_type}]" if show_types else name)


@service_app.command("call")
@one_line_errors
@server_options
def service_call(
    service: str,
    srv_type: Annotated[str, typer.Argument(metavar="TYPE", help="e.g. std_srvs/srv/SetBool")],
    request: Annotated[str, typer.Argument(help="Request fields, JSON or YAML: "
                                                "'{data: true}'.")] = "{}",
    timeout: Timeout = 5.0,
    server: ServerTarget = LOCAL_SERVER,
) -> None:
    """Call SERVICE of type TYPE with REQUEST; print the response as JSON."""
    fields = _fields(request, "the request")
    with server.connect("rlbridge-service-call") as bridge:
        response = bridge.call(service, srv_type, fields, timeout=timeout)
    typer.echo(json.dumps(response))


@param_app.command("get")
@one_line_errors
@server_options
def param_get(node: str, name: str, timeout: Timeout = 5.0,
              server: ServerTarget = LOCAL_SERVER) -> None:
    """Print the value of parameter NAME of NODE (JSON)."""
    with server.connect("rlbridge-param-get") as bridge:
        value = bridge.get_parameter(node, name, timeout=timeout)
    typer.echo(json.dumps(list(value) if isinstance(value, bytes) else value))


@param_app.command("set")
@one_line_errors
@server_options
def param_set(
    node: str,
    name: str,
    value: Annotated[str, typer.Argument(help="JSON or YAML: 2.5, true, text, [1, 2].")],
    timeout: Timeout = 5.0,
    server: ServerTarget = LOCAL_SERVER,
) -> None:
    """Set parameter NAME of NODE to VALUE."""
    parsed = parse_document(value, "the value")
    with server.connect("rlbridge-param-set") as bridge:
        bridge.set_parameter(node, name, parsed, timeout=timeout)
    typer.echo("Set parameter successful")


@param_app.command("list")
@one_line_errors
@server_options
def param_list(node: str, timeout: Timeout = 5.0, server: ServerTarget = LOCAL_SERVER) -> None:
    """List the parameter names of NODE."""
    with server.connect("rlbridge-param-list") as bridge:
        for name in bridge.list_parameters(node, timeout=timeout):
            typer.echo(name)


@action_app.command("send")
@one_line_errors
@server_options
def action_send(
    action: str,
    action_type: Annotated[str, typer.Argument(metavar="TYPE",
                                               help="e.g. test_msgs/action/Fibonacci")],
    goal: Annotated[str, typer.Argument(help="Goal fields, JSON or YAML: '{order: 5}'.")]
    = "{}",
    timeout: Annotated[float, option(
        "--timeout", "Seconds to wait for the goal to be accepted, and then for its result "
        "(0 = no limit for the result).")] = 5.0,
    server: ServerTarget = LOCAL_SERVER,
) -> None:
    """Send GOAL to ACTION; print each feedback and the result as JSON lines."""
    from rlbridge.errors import ChannelClosed

    fields = _fields(goal, "the goal")
    with server.connect("rlbridge-action-send") as bridge:
        handle = bridge.send_goal(action, action_type, fields, timeout=timeout)
        typer.echo("goal accepted", err=True)
        while True:
            try:
                typer.echo(json.dumps({"feedback": handle.feedback.read(timeout=0.25)}))
            except TimeoutError:
                continue
            except ChannelClosed:
                break
        result = handle.result(timeout=timeout or None)
        typer.echo(json.dumps({"result": result, "status": handle.status}))
        if handle.status != "succeeded":
            raise typer.Exit(1)


__all__ = ["action_app", "param_app", "parse_document", "service_app"]
