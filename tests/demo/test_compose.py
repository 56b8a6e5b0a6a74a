"""docker-compose.yml without Docker: its shape, then its services' commands as local processes.

There is no Docker engine on the machines this project is tested on, so the compose file is
checked in two ways that need none:

1. its structure: two services on one network, the controller pointed at the bridge service by
   name, the impaired-link service in its own profile sharing the bridge's network namespace;
2. its behaviour: each rlbridge service's ``command`` runs as a local process, with the service
   host name replaced by 127.0.0.1, port 7411 by a free port and ``/out`` by a temporary
   directory. They must find each other and track; then the bridge gets SIGTERM (what
   ``docker compose stop`` sends), must write its plot and report and exit 0, and the controller
   must notice the lost link and exit 3 (which ``restart: on-failure`` turns into a reconnect).
"""

from __future__ import annotations

import itertools
import json
import queue
import re
import shutil
import signal
import subprocess
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from localhost import rlbridge_command
from rlbridge.demo.vision import Lissajous
from waiting import wait_until

REPO = Path(__file__).resolve().parents[2]
COMPOSE = REPO / "docker-compose.yml"
DOCKERFILE = REPO / "Dockerfile"
COMPOSE_PORT = "7411"


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load(COMPOSE.read_text())
    return data


def test_compose_file_describes_bridge_and_controller_on_one_network(
        compose: dict[str, Any]) -> None:
    services = compose["services"]
    bridge, controller = services["bridge"], services["controller"]
    assert bridge["command"][:4] == ["rlbridge", "demo", "--role", "bridge"]
    assert controller["command"][:4] == ["rlbridge", "demo", "--role", "controller"]
    assert _option(controller["command"], "--host") == "bridge"  # the service name
    assert _option(bridge["command"], "--host") == "0.0.0.0"
    assert _option(bridge["command"], "--port") == _option(controller["command"], "--port")
    assert bridge["networks"] == controller["networks"]
    assert set(bridge["networks"]) <= set(compose["networks"])
    assert "bridge" in controller["depends_on"]
    probe = bridge["healthcheck"]["test"]
    assert probe[:3] == ["CMD", "rlbridge", "ping"]
    assert _option(probe, "--port") == _option(bridge["command"], "--port")
    assert controller["restart"] == "on-failure"
    assert {"7411:7411/tcp", "7411:7411/udp"} <= set(bridge["ports"])
    for name in ("bridge", "controller"):
        assert "profiles" not in services[name], f"{name} must start with a plain `up`"
    # Secure by default: both use the key on a volume only they mount.
    key = _option(bridge["command"], "--psk-file")
    assert key == _option(controller["command"], "--psk-file")
    assert key.startswith("/keys/")
    assert "keys:/keys" in bridge["volumes"]
    assert "keys:/keys:ro" in controller["volumes"]
    assert "keys" in compose["volumes"]


def test_impaired_link_service_is_optional_and_only_runs_tc(compose: dict[str, Any]) -> None:
    netem = compose["services"]["netem"]
    assert netem["profiles"] == ["impaired"]
    assert netem["network_mode"] == "service:bridge"
    assert "NET_ADMIN" in netem["cap_add"]
    script = netem["command"][2].replace("$$", "$")  # compose's escape for a literal $
    assert "tc qdisc replace dev eth0 root netem $NETEM" in script
    assert "NETEM" in netem["environment"]
    sh = shutil.which("sh")
    if sh is not None:  # parse only (-n): nothing is executed, no qdisc is touched
        subprocess.run([sh, "-n", "-c", script], check=True, timeout=10)


def test_dockerfile_installs_the_package_with_its_entry_point() -> None:
    text = DOCKERFILE.read_text()
    assert re.search(r"^FROM python:3\.11", text, re.MULTILINE)
    assert "COPY src ./src" in text
    assert 'pip install --no-cache-dir ".[plot]"' in text
    assert "iproute2" in text  # tc for the impaired-link service


# -- the services' commands, run here ----------------------------------------------------------
def _option(command: list[Any], name: str) -> str:
    return str(command[command.index(name) + 1])


def localize(command: list[Any], port: int, out: Path, keys: Path) -> list[str]:
    """A compose ``command`` for this machine (see the module docstring)."""
    args = [str(a) for a in command]
    assert args[0] == "rlbridge"
    local = rlbridge_command()
    for previous, arg in itertools.pairwise(args):
        if previous == "--host":
            local.append("127.0.0.1")  # "bridge" (the service name) or "0.0.0.0"
        elif previous == "--port":
            assert arg == COMPOSE_PORT
            local.append(str(port))
        elif arg.startswith("/out/"):
            local.append(str(out / arg.removeprefix("/out/")))
        elif arg.startswith("/keys/"):  # the shared volume: one directory for both services
            local.append(str(keys / arg.removeprefix("/keys/")))
        else:
            local.append(arg)
    return local


class Service:
    """A running service: its process and a thread that collects its output lines."""

    def __init__(self, name: str, args: list[str]) -> None:
        self.name = name
        self.proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, env=_env())
        self.lines: queue.Queue[str] = queue.Queue()
        self.output: list[str] = []
        self._reader = threading.Thread(target=self._read, name=f"read {name}", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.output.append(line)
            self.lines.put(line)

    def wait_for_line(self, predicate: Callable[[str], bool], timeout: float) -> str:
        def matching() -> str | None:
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                return None
            return line if predicate(line) else None

        found: str = wait_until(matching, lambda: f"a matching line from {self.name}; it "
                                f"said:\n{''.join(self.output)}", timeout=timeout, interval=0)
        return found

    def wait(self, timeout: float) -> int:
        code = self.proc.wait(timeout)
        self._reader.join(timeout=5)
        return code

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)
        self._reader.join(timeout=5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


def _env() -> dict[str, str]:
    import os

    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("PYTHONWARNINGS", None)
    return env


@pytest.fixture
def services() -> Iterator[dict[str, Service]]:
    running: dict[str, Service] = {}
    yield running
    for service in running.values():
        service.stop()


@pytest.mark.timeout(300)  # bounds below are for a loaded 2-core machine, not the usual ~15 s
def test_compose_services_run_locally_track_and_stop_in_order(
        compose: dict[str, Any], services: dict[str, Service], tmp_path: Path,
        free_port: Callable[[], int]) -> None:
    port = free_port()
    spec = compose["services"]
    keys = tmp_path / "keys"  # the named volume both services mount
    keys.mkdir()
    # `depends_on` order, as compose starts them; the controller retries until the bridge is up.
    services["bridge"] = Service("bridge",
                                 localize(spec["bridge"]["command"], port, tmp_path, keys))
    services["controller"] = Service("controller",
                                     localize(spec["controller"]["command"], port, tmp_path,
                                              keys))
    bridge, controller = services["bridge"], services["controller"]

    controller.wait_for_line(lambda line: "controller connected" in line, timeout=40)
    assert (keys / "demo.key").stat().st_mode & 0o077 == 0  # made by the bridge, private
    health = localize(spec["bridge"]["healthcheck"]["test"][1:], port, tmp_path, keys)
    probe = subprocess.run(health, capture_output=True, text=True, timeout=60, check=False)
    assert probe.returncode == 0, probe.stderr  # the bridge is healthy (a keyed one too)
    # The bridge prints one line a second with the controller's state as it reported it; 4 s
    # of tracking leave enough sub-sampled angles for the checks below even when the machine
    # is so loaded that few arrive per second.
    bridge.wait_for_line(lambda line: _tracking_after(line, 4.0), timeout=60)

    bridge.proc.send_signal(signal.SIGTERM)  # `docker compose stop`
    assert bridge.wait(timeout=60) == 0, "".join(bridge.output)
    controller.wait_for_line(lambda line: "state -> lost-link" in line, timeout=20)
    probe = subprocess.run(health, capture_output=True, text=True, timeout=60, check=False)
    assert probe.returncode == 1, probe  # and unhealthy once it is gone
    assert probe.stderr.startswith("rlbridge: error: cannot reach 127.0.0.1:"), probe.stderr

    report = json.loads((tmp_path / "report.json").read_text())
    assert report["reason"] == "signal"
    assert "tracking" in [s for _, s in report["states"]]
    assert report["diagnostics"]["link"] == "connected"
    assert sum(report["angles_received"].values()) > 100
    assert report["tracking"]["pan"]["samples"] >= 20
    # It tracks: well under the error of a camera that does not move (test_demo.py says why).
    assert report["tracking"]["pan"]["rms_mrad"] < 0.5 * Lissajous().pan_amplitude / 2**0.5 * 1e3
    assert (tmp_path / "pan_tilt.png").read_bytes().startswith(b"\x89PNG")

    # `docker compose start bridge`: the controller, never restarted, reconnects and tracks.
    again = services["bridge again"] = Service(
        "bridge", localize(spec["bridge"]["command"], port, tmp_path / "again", keys))
    controller.wait_for_line(lambda line: "state -> tracking" in line, timeout=60)
    assert controller.proc.poll() is None, "".join(controller.output)
    again.wait_for_line(lambda line: _tracking_after(line, 2.0), timeout=60)
    controller.proc.send_signal(signal.SIGTERM)
    assert controller.wait(timeout=60) == 0, "".join(controller.output)

    # The restarted bridge counts only the angles sent to it: none of the first bridge's
    # (thousands of them) show up as lost.
    again.proc.send_signal(signal.SIGTERM)
    assert again.wait(timeout=60) == 0, "".join(again.output)
    second = json.loads((tmp_path / "again" / "report.json").read_text())
    first_received = sum(report["angles_received"].values())
    received = sum(second["angles_received"].values())
    assert received > 0
    # Before, "sent" was every angle since the controller started, so "lost" was at least
    # what the first bridge had received; now it is what was sent to this bridge.
    assert second["angles_sent"] < received + first_received // 4, (second, first_received)
    assert second["angles_lost"] == max(0, second["angles_sent"] - received)
    assert second["diagnostics"]["session"] == 1  # the controller's second session


def _tracking_after(line: str, seconds: float) -> bool:
    match = re.match(r"t=\s*([\d.]+)s tracking ", line)
    return match is not None and float(match.group(1)) >= seconds
